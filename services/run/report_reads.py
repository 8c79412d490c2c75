"""The report's decoding of the recordings, started while the run goes on.

The report decodes every recording once (``services.results.decoding``): on the valley in
one process, 7 s after the last reproduction, while during the reproductions one core of
two stepped the cell and the other had little to do.  ``ReportReads`` decodes each
recording in a process beside the run as soon as the recording is complete and what the
report takes from it is known (after the learn stage: the phase mapping its reproductions
are scored with, the figures' view), and hands the report what it decoded; the report
decodes only what is not there or whose reading has changed since (``decode_episodes``
compares them), so the report is the same either way.  Lockstep only: on the realtime
clock that work would take CPU the 1 kHz loop needs; not in a sweep, whose runs take the
CPUs already (``workers`` 1); not before the recordings are worth a process's start
(``PARALLEL_READ_BYTES``, as the report decides: a smoke's are not).  The same process
draws the figures that need no reproduction (the demonstrations', the learning's) while
the reproductions run (``start``): the valley's figures after its report 2.1 -> 0.5 s,
the same files byte for byte.  A process beside the run that is lost (killed) costs the
run nothing: its work not done is done in the run's process when the reads end
(``services.runtime.threads.FallbackMap``, as for the learn stage's pool).
"""

from __future__ import annotations

import contextlib
from concurrent.futures.process import BrokenProcessPool

from services.results.decoding import PARALLEL_READ_BYTES, decode_episode, recordings_size
from services.runtime.threads import FallbackMap, process_map

WHAT = "the report's reader beside the run"


class ReportReads:
    """As a context manager: on a clean exit, what was started is waited for and kept in
    ``decoded`` ((reading, DecodedEpisode) pairs, for ``write_report``); on a failure the
    process is terminated with the run and the report decodes everything itself.

    The reproductions end with recordings still waiting for the process beside (on the
    valley, ten of twenty: it decodes one in ~1.2 s while the cell takes the CPUs, ~0.55 s
    after): this process then takes them back from the end of the queue, one at a time,
    and decodes them itself while the process beside goes on from its front."""

    def __init__(self, wanted: bool, at_least: int = PARALLEL_READ_BYTES, say=print):
        """``at_least``: the bytes of recordings that make starting the process worth it;
        ``say``: told once if the process is lost."""
        self.wanted, self.at_least, self._say = wanted, at_least, say
        self.decoded: list = []
        self.ahead: dict = {}  # name -> the result of work done beside (``start``), once the reads end
        self._started: list = []  # (reading, the future of its decoding; None: to be done here)
        self._ahead: list = []  # (name, fn, args, the future of fn(*args); None: to be done here)
        self._stack = contextlib.ExitStack()
        self._pool = None  # the process's pool (submit)
        self._map = None  # its map, a FallbackMap: ``lost`` once the process is gone
        self.taken_back = 0  # recordings the process beside had not begun when the reads ended

    def catch_up(self, readings) -> None:
        """Start decoding every reading of ``readings`` (the report's, as of now) not started yet."""
        if not self._beside(readings):
            return
        for reading in readings:
            if not any(reading == started for started, _ in self._started):
                self._started.append((reading, self._submit(decode_episode, reading)))

    def start(self, name: str, fn, args: tuple, readings) -> bool:
        """Run ``fn(*args)`` in the process beside the run, after what it has been given to
        decode, when the recordings ``readings`` are worth that process; its result in
        ``ahead[name]`` once the reads end (none if it failed: the report's own work then
        does it).  Whether it was started."""
        if not self._beside(readings):
            return False
        self._ahead.append((name, fn, args, self._submit(fn, *args)))
        return True

    def _beside(self, readings) -> bool:
        """Whether the process beside the run is there (started now, if wanted and worth it)."""
        if not self.wanted:
            return False
        if self._map is None:
            if recordings_size(readings) < self.at_least:
                return False
            self._pool = self._stack.enter_context(process_map(1, beside=True))
            self._map = FallbackMap(self._pool, self._say, WHAT)
        return True

    def _submit(self, fn, *args):
        """``fn(*args)`` handed to the process beside: its future, or None once that process
        is lost (then it is done here when the reads end)."""
        if self._map.lost is None:
            try:
                return self._pool.submit(fn, *args)
            except BrokenProcessPool as exc:
                self._map.lose(exc)
        return None

    def _result(self, future, fn, args):
        """What the process beside made of ``fn(*args)``, or this process if it was lost;
        None if it failed (the report's own work does it again and says what is wrong)."""
        if future is not None:
            try:
                return future.result()
            except BrokenProcessPool as exc:
                self._map.lose(exc)
            except Exception:  # noqa: BLE001 - see above
                return None
        return _here(fn, args)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        started, self._started = self._started, []
        ahead, self._ahead = self._ahead, []
        if exc_type is None:
            try:
                decoded = [None] * len(started)
                end = len(started)
                while end and (started[end - 1][1] is None or started[end - 1][1].cancel()):
                    end -= 1  # not begun over there: taken back, from the end
                    self.taken_back += 1
                    decoded[end] = _here(decode_episode, (started[end][0],))
                for i in range(end):
                    decoded[i] = self._result(started[i][1], decode_episode, (started[i][0],))
                self.decoded = [(reading, d) for (reading, _), d in zip(started, decoded) if d is not None]
                for name, fn, args, future in ahead:
                    got = self._result(future, fn, args)
                    if got is not None:
                        self.ahead[name] = got
            except BaseException as waiting:  # Ctrl-C while waiting: the process goes with the run
                self._stack.__exit__(type(waiting), waiting, waiting.__traceback__)
                raise
        return self._stack.__exit__(exc_type, exc, tb)


def _here(fn, args: tuple):
    """``fn(*args)`` in this process; None if it failed (the report's own work does it again
    and says what is wrong)."""
    try:
        return fn(*args)
    except Exception:  # noqa: BLE001 - see above
        return None
