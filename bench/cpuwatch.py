"""CPU time per process over a run, and what the rest of the machine used meanwhile.

Samples utime + stime of the processes whose command line contains a marker (a
run id) from /proc/<pid>/stat, and the machine's busy time from /proc/stat,
once a second in a thread.  ``usage(t0, t1)`` gives each process's share of one
CPU between two CLOCK_MONOTONIC instants (the samples nearest inside), and
"other": busy time of everything else on the machine (other users' jobs make a
timing run meaningless; the benchmarks print it so a reader can tell).
"""

from __future__ import annotations

import os
import threading
import time

from services.transport.launch import PROGRAM_MODULE

TICK = os.sysconf("SC_CLK_TCK")


def _machine_busy() -> int:
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return sum(v) - v[3] - v[4]  # minus idle and iowait


def _processes(marker: str) -> dict:
    out = {}
    me = os.getpid()
    for p in os.listdir("/proc"):
        if not p.isdigit() or int(p) == me:
            continue
        try:
            with open(f"/proc/{p}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace")
            if marker not in cmd:
                continue
            with open(f"/proc/{p}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        # a service is "python -m services.cli.roles ROLE ..." (services.transport.launch)
        name = cmd.split(f"-m {PROGRAM_MODULE} ", 1)[1].split()[0] if f"-m {PROGRAM_MODULE} " in cmd else f"pid {p}"
        out[int(p)] = (name, int(fields[11]) + int(fields[12]))
    return out


class CpuWatch:
    def __init__(self, marker: str, extra_pids=(), period: float = 1.0):
        self.marker = marker
        self.extra = {int(pid): name for pid, name in dict(extra_pids).items()}
        self.period = period
        self.samples = []  # (monotonic ns, machine busy ticks, {pid: (name, ticks)})
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def add(self, pid: int, name: str) -> None:
        self.extra[int(pid)] = name

    def _sample(self):
        procs = _processes(self.marker)
        for pid, name in list(self.extra.items()):
            try:
                with open(f"/proc/{pid}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
                procs[pid] = (name, int(fields[11]) + int(fields[12]))
            except OSError:
                pass
        mine = os.times()
        procs[os.getpid()] = ("bench (this process)", int((mine.user + mine.system) * TICK))
        self.samples.append((time.monotonic_ns(), _machine_busy(), procs))

    def _run(self):
        while not self._stop.is_set():
            self._sample()
            self._stop.wait(self.period)

    def start(self) -> "CpuWatch":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()

    def usage(self, t0_ns: int, t1_ns: int) -> dict:
        """{name: percent of one CPU} between the samples nearest inside [t0, t1], plus
        'other' (the rest of the machine) and 'seconds' (the span measured)."""
        inside = [s for s in self.samples if t0_ns <= s[0] <= t1_ns]
        if len(inside) < 2:
            return {}
        (ta, ba, pa), (tb, bb, pb) = inside[0], inside[-1]
        span = (tb - ta) / 1e9
        out = {}
        ours = 0
        for pid, (name, ticks) in pb.items():
            d = ticks - pa[pid][1] if pid in pa else ticks  # started inside the span: all of its time
            ours += d
            out[name] = out.get(name, 0.0) + d / TICK / span * 100
        out["other"] = max(0.0, (bb - ba) - ours) / TICK / span * 100
        out["seconds"] = span
        return out
