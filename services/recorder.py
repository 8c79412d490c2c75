"""recorder: everything of a run, byte for byte, to MCAP - one file per episode.

Subscribes to ``etar/<run_id>/**`` and writes every sample's payload unchanged
(``services.recording.EpisodeWriter``: chunked, zstd, a JSON Schema per
channel so Foxglove plots the wrench and phase topics, the scenario
attached).  Control: ``begin_episode`` (path, kind, index, scenario text),
``end_episode`` (waits until every listed topic has reached ``last_seq``, then
finalises the file), ``status``, ``shutdown``.  SIGINT/SIGTERM finalise the open
file: nothing already recorded is lost.
"""

from __future__ import annotations

import argparse
import re
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from services.recording import EpisodeWriter
from services.runtime import topics
from services.runtime.service import Service, now_ns
from services.runtime.session import ZenohOptions, add_zenoh_arguments, zenoh_options

_SEQ = re.compile(rb'^\{"seq":(-?\d+)')


@dataclass(frozen=True)
class RecorderConfig:
    run_id: str
    zenoh: ZenohOptions
    sched_fifo: int = 0  # SCHED_FIFO priority, 0: none
    cpus: tuple = ()  # CPU affinity of the whole process, (): any
    out_dir: str = "recordings"  # made absolute by the CLI: the folder every episode path is relative to


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


class RecorderProcess:
    def __init__(self, config: RecorderConfig, svc: Service):
        self.config = config
        self.svc = svc
        self.writer: EpisodeWriter | None = None
        self._lock = threading.Condition()
        self._last_seq: dict[str, int] = {}
        self.total = 0
        prefix = topics.prefix(config.run_id) + "/"
        self._prefix_len = len(prefix)
        self._sub = svc.session.declare_subscriber(prefix + "**", svc.profile.wrap(self.on_sample))

    def on_sample(self, sample) -> None:
        recv = now_ns()
        key = str(sample.key_expr)
        raw = sample.payload.to_bytes()
        m = _SEQ.match(raw)
        with self._lock:
            if self.writer is not None:
                self.writer.add(key, raw, recv)
                self.total += 1
            if m:
                topic = key[self._prefix_len:]
                seq = int(m.group(1))
                if seq > self._last_seq.get(topic, -1):
                    self._last_seq[topic] = seq
                self._lock.notify_all()

    def begin(self, p: dict) -> str:
        path = episode_path(self.config.out_dir, p["path"])
        path.parent.mkdir(parents=True, exist_ok=True)
        with self._lock:
            if self.writer is not None:
                self.writer.finish()
            self.writer = EpisodeWriter(path, run_id=self.config.run_id, episode_kind=p.get("kind", "episode"),
                                        episode_index=int(p.get("index", 0)), scenario_text=p.get("scenario"),
                                        metadata=p.get("metadata") or {})
        return str(path)

    def end(self, p: dict) -> dict:
        last = int(p.get("last_seq", -1))
        wanted = list(p.get("topics", []))
        deadline = time.monotonic() + float(p.get("timeout", 10.0))
        with self._lock:
            while any(self._last_seq.get(t, -1) < last for t in wanted) and time.monotonic() < deadline:
                self._lock.wait(0.05)
            lagging = [t for t in wanted if self._last_seq.get(t, -1) < last]
            writer, self.writer = self.writer, None
        if writer is None:
            raise ValueError("no episode is being recorded")
        writer.finish()
        return {"messages": writer.messages_written, "bad_payloads": writer.bad_payloads, "lagging": lagging}

    def close(self) -> None:
        with self._lock:
            if self.writer is not None:
                self.writer.finish()
                self.writer = None
        self._sub.undeclare()

    def serve(self) -> None:
        try:
            self.svc.serve({"begin_episode": lambda p: {"path": self.begin(p)}, "end_episode": self.end},
                           status=lambda: {"total": self.total, "recording": self.writer is not None,
                                           "last_seq": self._last_seq})
        finally:
            self.close()


def main(config: RecorderConfig) -> int:
    with Service("recorder", config.run_id, config.zenoh, sched_fifo=config.sched_fifo,
                 cpus=config.cpus) as svc:
        proc = RecorderProcess(config, svc)
        svc.log(f"ready: recording etar/{config.run_id}/** into {config.out_dir}")
        proc.serve()
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="etar-recorder", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-id", required=True)
    parser.add_argument("--clock", choices=("lockstep", "realtime"), default="lockstep",
                        help="accepted for symmetry: the recorder records whatever arrives")
    parser.add_argument("--out-dir", default="recordings",
                        help="folder the episode files go into; the runner names them relative to it "
                             "(default ./recordings, resolved when the recorder starts)")
    add_zenoh_arguments(parser)
    return parser


def cli(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return main(RecorderConfig(run_id=args.run_id, zenoh=zenoh_options(args), out_dir=str(Path(args.out_dir).resolve()),
                               sched_fifo=args.sched_fifo, cpus=args.cpus))


if __name__ == "__main__":
    sys.exit(cli())
