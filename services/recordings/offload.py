"""The MCAP writer of an in-process run, in a helper process fed over a pipe.

    python -m services.recordings.offload --writer-process   (started by WriterProcess, not by hand)
"""

from __future__ import annotations

import contextlib
import os
import pickle
import signal
import threading
from pathlib import Path

from services.recordings.format import RecordingError
from services.recordings.writer import EpisodeWriter


# what the helper's writer counted, sent back when it finishes a file
FINISH_COUNTS = ("messages_written", "bad_payloads", "visual_errors", "visual_undecodable")


class WriterProcess:
    """``EpisodeWriter`` s run in a helper process, fed over a pipe in batches.

    What an in-process run does instead of writing MCAP on its own thread: every
    node of the run shares one CPU and its GIL, and turning each message into MCAP
    records (the mcap library's Python) took a fifth of each simulated millisecond.
    The helper writes the same files with the same writer.  ``open`` and ``finish``
    wait for the helper (an error names the file); ``add`` only queues.  If this
    process dies, the helper finishes the open file with what it was sent."""

    BATCH = 2000  # messages per hand-over

    def __init__(self, opener=EpisodeWriter):
        """``opener(path, **options)``: what the helper opens an episode's file with,
        ``EpisodeWriter`` or something called like it and answering like it (the recorder's
        writer that adds the visual topics), picklable: the helper gets its own copy."""
        import subprocess
        import sys

        # its own interpreter (not multiprocessing: that re-imports the caller's main
        # script, and forking copies the run's threads), in its own session: Ctrl-C (or a
        # SIGTERM to the run's process group) is the run's to handle, which finishes the
        # episode's file through it; if the run dies, the pipe's end finishes the file.
        # The replies come on a pipe of their own, and its stdout goes to stderr: whatever
        # the helper prints (numba's NUMBA_DEBUG_CACHE lines as its imports load kernels)
        # cannot corrupt them
        replies, reply_end = os.pipe()
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "services.recordings.offload", "--writer-process", str(reply_end)],
                stdin=subprocess.PIPE, stdout=2, stderr=None, start_new_session=True, pass_fds=(reply_end,))
        except BaseException:
            os.close(replies)
            raise
        finally:
            os.close(reply_end)  # the helper's now: its end closing is what the parent reads as gone
        self._replies = os.fdopen(replies, "rb")
        _widen(self._proc.stdin)
        self._send(("opener", opener))

    def _call(self, *request):
        try:
            with _interrupts_held():
                self._send(request)
                ok, value = pickle.load(self._replies)
        except (EOFError, OSError, pickle.UnpicklingError) as exc:
            raise RecordingError(f"the MCAP writer process is gone ({type(exc).__name__}: {exc}; exit code "
                                 f"{self._proc.poll()})") from None
        if not ok:
            raise RecordingError(value)
        return value

    def _send(self, request) -> None:
        pickle.dump(request, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        self._proc.stdin.flush()

    def open(self, path, **kwargs) -> "OffloadedEpisodeWriter":
        self._call("open", str(path), kwargs)
        return OffloadedEpisodeWriter(self, Path(path))

    def send(self, batch: list) -> None:
        try:
            self._send(("add", batch))
        except OSError as exc:
            raise RecordingError(f"the MCAP writer process is gone ({exc}; exit code {self._proc.poll()})") from None

    def close(self) -> None:
        try:
            self._send(("close",))
            self._proc.stdin.close()
        except OSError:
            pass
        try:
            self._proc.wait(10)
        except Exception:
            self._proc.kill()
            self._proc.wait()
        self._replies.close()


class OffloadedEpisodeWriter:
    """The parent's side of one file a ``WriterProcess`` writes (``EpisodeWriter``'s interface)."""

    def __init__(self, process: WriterProcess, path: Path):
        self._process = process
        self.path = path
        self._batch: list = []
        # as the helper's writer counted them, once finished
        self.messages_written = self.bad_payloads = self.visual_errors = self.visual_undecodable = 0
        self._finished = False

    def add(self, key_expr: str, payload: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        if self._finished:
            raise RecordingError(f"{self.path}: add() after finish()")
        self._batch.append((key_expr, bytes(payload), log_time_ns, publish_time_ns))
        if len(self._batch) >= WriterProcess.BATCH:
            self._hand_over()

    def finish(self) -> None:
        if self._finished:
            return
        self._finished = True
        if self._batch:
            self._hand_over()
        for name, value in self._process._call("finish").items():
            setattr(self, name, value)

    @property
    def finished(self) -> bool:
        return self._finished

    def _hand_over(self) -> None:
        with _interrupts_held():  # sent and forgotten together: sent twice, the file would hold it twice
            self._process.send(self._batch)
            self._batch = []


# a batch's pickle (2000 messages of ~700 bytes: 1.4 MB) into a pipe of Linux's
# default 64 kB went in ~20 writes, each waiting for the helper to read: 0.95 ms of this
# process's CPU a batch; into a pipe of 1 MB (Linux's default limit for an unprivileged
# process, /proc/sys/fs/pipe-max-size), 0.62 ms
PIPE_BYTES = 1 << 20


def _widen(pipe) -> None:
    """The pipe to the helper as wide as the system lets it be (Linux); as it is elsewhere."""
    try:
        import fcntl

        fcntl.fcntl(pipe.fileno(), fcntl.F_SETPIPE_SZ, PIPE_BYTES)
    except (ImportError, AttributeError, OSError):
        pass


@contextlib.contextmanager
def _interrupts_held():
    """Ctrl-C and SIGTERM wait for the end of the block, on the main thread (where Python
    runs their handlers).  An in-process run's interrupt is a KeyboardInterrupt raised
    wherever the run is: raised half-way through a request to the helper, it left half a
    pickle in the pipe, the next request (the finish the interrupt leads to) read as
    garbage, and the episode's file was lost.  A second signal in the block is not held:
    the run's way out of a hang."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held, saved = [], {}

    def hold(signum, frame):
        if held:  # the second: not held
            saved[signum](signum, frame)
        else:
            held.append(signum)

    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            if callable(signal.getsignal(sig)):  # a Python handler (raising, say): not the default's exit
                saved[sig] = signal.signal(sig, hold)
        yield
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)
        if held:
            saved[held[0]](held[0], None)


def _writer_main(requests, replies) -> None:
    """The helper process: open / add / finish / close requests, until the pipe closes."""
    writer = None
    opener = EpisodeWriter

    def reply(value) -> None:
        pickle.dump(value, replies, protocol=pickle.HIGHEST_PROTOCOL)
        replies.flush()

    failed = None  # why the open file took no more (a full disk): the parent hears it at finish
    try:
        while True:
            try:
                request = pickle.load(requests)
            except EOFError:
                return  # the parent is gone: the finally below finishes the open file
            kind = request[0]
            if kind == "add":
                if writer is not None and failed is None:
                    try:
                        for key, raw, log, pub in request[1]:
                            writer.add(key, raw, log, pub)
                    except Exception as exc:  # noqa: BLE001 - said at finish, naming the file
                        failed = str(exc) if isinstance(exc, RecordingError) else f"{type(exc).__name__}: {exc}"
                continue
            if kind == "close":
                return
            if kind == "opener":
                opener = request[1]
                continue
            try:
                if kind == "open":
                    if writer is not None:
                        _finish_quietly(writer)
                    writer, failed = None, None
                    writer = opener(request[1], **request[2])
                    reply((True, None))
                elif kind == "finish":
                    w, writer = writer, None
                    if w is None:
                        raise RecordingError("no episode is being recorded")
                    if failed is not None:
                        _finish_quietly(w)
                        raise RecordingError(failed)
                    w.finish()
                    reply((True, {name: getattr(w, name, 0) for name in FINISH_COUNTS}))
            except Exception as exc:  # the parent raises it, naming the file
                reply((False, str(exc) if isinstance(exc, RecordingError) else f"{type(exc).__name__}: {exc}"))
    finally:
        if writer is not None:
            _finish_quietly(writer)


def _finish_quietly(writer) -> None:
    """Finish a file whose failure has been (or cannot be) said: it keeps what it holds."""
    try:
        writer.finish()
    except Exception:  # noqa: BLE001 - the file's failure is reported where it was met
        pass


if __name__ == "__main__":
    import sys

    if len(sys.argv) != 3 or sys.argv[1] != "--writer-process" or not sys.argv[2].isdigit():
        sys.exit("python -m services.recordings.offload --writer-process FD: the MCAP writer of an in-process run, "
                 "replying on FD (started by services.recordings.offload.WriterProcess, not by hand)")
    _writer_main(sys.stdin.buffer, os.fdopen(int(sys.argv[2]), "wb"))
    from services.runtime.threads import exit_without_teardown

    exit_without_teardown()  # every file is finished and closed (``_writer_main``)
