"""The recorder node: everything of a run, byte for byte, to MCAP - one file per episode.

Takes every message of the run (``"**"``, undecoded) and writes its payload
unchanged (a payload over 64 KiB is counted, not recorded).  The files
(``services.recordings.writer``) are chunked and zstd-compressed, with a JSON
Schema per channel so Foxglove plots the wrench and phase topics, and the
scenario attached; beside the run's own topics go Foxglove's visual topics
(``--visual-rate-hz``).  Control: ``begin_episode`` (path relative to
``--out-dir``, kind, index, scenario text), ``end_episode`` (finalises the file;
says which listed topics had not reached the cycle it names), ``status``.
Stopping the recorder finalises an open file: nothing already recorded is lost.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from pathlib import Path

from etar.parsing import cannot_write_in
from services.recordings.offload import WriterProcess
from services.runtime import topics
from services.runtime.bus import Node, Subscription
from services.runtime.config import FieldError, option
from services.runtime.messages import MAX_PAYLOAD_BYTES, SEQ_PREFIX
from services.runtime.visual_topics import VISUAL_RATE_HZ, check_visual_rate
from services.foxglove.tap import VisualRecordings


@dataclass(frozen=True)
class RecorderConfig:
    out_dir: str = option("recordings", "folder the episode files go into (made if missing; a file there, or a "
                                        "folder this user may not write in, is refused); the runner names the "
                                        "files relative to it", metavar="DIR")
    writer_process: bool = option(False, "write the MCAP files from a helper process (what an in-process run "
                                         "does: its nodes share one CPU)")
    visual_rate_hz: float = option(VISUAL_RATE_HZ, "rate of Foxglove's visual topics (/viz/...: the arm, the world, "
                                                   "wrench, stiffness, phase) recorded beside the run's own, Hz, "
                                                   "at most one per FRI cycle (1000); 0: none", metavar="HZ")

    def __post_init__(self):
        check_visual_rate(self.visual_rate_hz, "visual_rate_hz", none=True)
        check_out_dir(self.out_dir)


def check_out_dir(out_dir) -> None:
    """FieldError unless the recorder can put its files in ``out_dir``: a folder, or one it
    can make (its nearest existing parent a folder it may write in).  Nothing is left made."""
    path = Path(out_dir)
    if not str(out_dir).strip():
        raise FieldError("out_dir", "expected a folder", "''")
    if path.exists():
        if not path.is_dir():
            raise FieldError("out_dir", "not a folder (it is a file)", out_dir)
        if not os.access(path, os.W_OK | os.X_OK):
            raise FieldError("out_dir", "this user may not write in that folder", out_dir)
        why = cannot_write_in(path)
        if why:
            raise FieldError("out_dir", f"nothing can be made in that folder ({why})", out_dir)
        return
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise FieldError("out_dir", f"cannot be made: {parent} is a file, not a folder", out_dir)
    if not os.access(parent, os.W_OK | os.X_OK):
        raise FieldError("out_dir", f"cannot be made: this user may not write in {parent}", out_dir)
    why = cannot_write_in(parent)
    if why:
        raise FieldError("out_dir", f"cannot be made in {parent} ({why})", out_dir)


def episode_path(out_dir, name) -> Path:
    """Where the episode ``name`` goes: a path relative to ``out_dir``, the one stated
    folder of this recorder.  An absolute path or one that climbs out is refused: a
    runner and a recorder that disagree about the working directory (one relative
    folder joined to another) once wrote out/valley/recordings/out/valley/recordings/."""
    rel = Path(str(name))
    if not str(name) or rel.is_absolute() or ".." in rel.parts:
        raise ValueError(f"episode path {str(name)!r}: expected a file name relative to the recorder's "
                         f"--out-dir ({out_dir}), not absolute and without '..'")
    return Path(out_dir) / rel


class RecorderNode(Node):
    name = "recorder"

    def __init__(self, config: RecorderConfig, bus, clock, *, run_id: str, mode: str = "lockstep", **_):
        super().__init__(bus, clock)
        self.run_id = topics.check_run_id(run_id)
        self.out_dir = Path(config.out_dir).resolve()
        self.prefix = topics.prefix(run_id) + "/"
        # one key string per topic: the writer's hand-over pickles a repeated object once per batch
        self._keys: dict[str, str] = {}
        self.writer = None  # the open episode's (services.foxglove.tap.VisualRecording, or the helper's)
        self.lock = threading.Condition()  # a transport waits on it for messages still in flight
        self.last_seq: dict[str, int] = {}
        self.total = 0
        self.oversized = 0  # payloads over MAX_PAYLOAD_BYTES, not recorded
        self.subscriptions = [Subscription("**", self.on_sample, decode=False)]
        # the episode's files with their visual topics: opened here, or by the helper process
        # in an in-process run, where the scene is drawn too (one CPU carries every node)
        self._open = VisualRecordings(config.visual_rate_hz)
        self._writer_process = WriterProcess(self._open) if config.writer_process else None
        self.visual_errors = self.visual_undecodable = 0  # of the episodes finished

    def on_sample(self, topic: str, recv_ns: int, raw: bytes, message: dict | None = None) -> None:
        self.take(((topic, recv_ns, raw, message),))

    def take(self, samples) -> None:
        """Messages of the run in the order they came, each (topic, receive time, payload, the
        decoded message, or only its (seq, sent_ns), or None): one at a time from a transport
        (``on_sample``), or a cycle's at once (``services.transport.fused``, which makes a
        message's dict only when a node of the process reads it)."""
        keys = self._keys
        with self.lock:
            writer = self.writer
            try:
                for topic, recv_ns, raw, message in samples:
                    if len(raw) > MAX_PAYLOAD_BYTES:
                        # no receiver reads it: recording it would only let a foreign peer fill the disk
                        self.oversized += 1
                        continue
                    if message is None:
                        m = SEQ_PREFIX.match(raw)
                        seq, sent = (int(m.group(1)) if m else None), None
                    elif type(message) is tuple:
                        seq, sent = message
                    else:
                        seq, sent = message["seq"], message["sent_ns"]
                    try:
                        if writer is not None:
                            # a message already decoded (one process) needs no decoding for its publish time
                            key = keys.get(topic)
                            if key is None:
                                key = keys[topic] = self.prefix + topic
                            writer.add(key, raw, recv_ns, sent)
                            self.total += 1
                    finally:
                        # arrived, even when the file could not take it (a full disk): ending the
                        # episode then says so at once instead of waiting for it to be written
                        if seq is not None and seq > self.last_seq.get(topic, -1):
                            self.last_seq[topic] = seq
            finally:
                self.lock.notify_all()

    def lagging(self, wanted, last: int) -> list:
        """The topics among ``wanted`` whose newest message is older than cycle ``last``."""
        return [t for t in wanted if self.last_seq.get(t, -1) < last]

    def handlers(self):
        return {"begin_episode": lambda p: {"path": self.begin(p)}, "end_episode": self.end}

    def begin(self, p: dict) -> str:
        path = episode_path(self.out_dir, p["path"])
        path.parent.mkdir(parents=True, exist_ok=True)
        with self.lock:
            if self.writer is not None:
                self._finish(self.writer)
            options = dict(run_id=self.run_id, episode_kind=p.get("kind", "episode"),
                           episode_index=int(p.get("index", 0)), scenario_text=p.get("scenario"),
                           metadata=p.get("metadata") or {})
            if self._writer_process is not None:
                self.writer = self._writer_process.open(path, **options)
            else:
                self.writer = self._open(path, **options)
        return str(path)

    def end(self, p: dict) -> dict:
        with self.lock:
            lagging = self.lagging(list(p.get("topics", [])), int(p.get("last_seq", -1)))
            writer, self.writer = self.writer, None
        if writer is None:
            raise ValueError("no episode is being recorded")
        self._finish(writer)
        return {"messages": writer.messages_written, "bad_payloads": writer.bad_payloads, "lagging": lagging}

    def _finish(self, writer) -> None:
        writer.finish()
        with self.lock:
            self.visual_errors += writer.visual_errors
            self.visual_undecodable += writer.visual_undecodable

    def status(self) -> dict:
        return {"total": self.total, "recording": self.writer is not None, "last_seq": self.last_seq,
                "oversized": self.oversized,
                # of the episodes finished (an in-process run's helper counts them until then)
                "visual_errors": self.visual_errors, "visual_undecodable": self.visual_undecodable}

    def close(self) -> None:
        with self.lock:
            try:
                if self.writer is not None:
                    self._finish(self.writer)
                    self.writer = None
            finally:
                if self._writer_process is not None:
                    self._writer_process.close()
                    self._writer_process = None
