"""Periodic loops on absolute deadlines, with their timing statistics.

``LoopTiming`` records, per cycle, the wake-up lateness (wake - deadline), the
execution time and whether the cycle overran its period (a deadline miss),
plus the longest run of consecutive misses (FRI drops out on consecutive
misses).  ``AbsoluteDeadlineTimer`` sleeps to absolute deadlines; after an
overrun it skips to the next future deadline rather than trying to catch up
(one stall must not snowball into a burst of late cycles).
"""

from __future__ import annotations

import ctypes
import os
from dataclasses import dataclass, field

from services.runtime.bus import MonotonicClock
from services.runtime.timing import Histogram


def set_timer_slack(ns: int = 1) -> bool:
    """Linux: shrink the timer slack so sleeps wake closer to their deadline."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        PR_SET_TIMERSLACK = 29
        return libc.prctl(PR_SET_TIMERSLACK, ns, 0, 0, 0) == 0
    except OSError:
        return False


def try_sched_fifo(priority: int = 50) -> bool:
    """Switch this process to SCHED_FIFO if permitted; True if it worked."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (PermissionError, OSError, AttributeError):
        return False


@dataclass
class LoopTiming:
    """Per-cycle wake-up lateness, execution time and deadline misses of one loop."""

    period_ns: int
    lateness: Histogram = field(default_factory=Histogram)
    execution: Histogram = field(default_factory=Histogram)
    misses: int = 0
    longest_miss_run: int = 0
    _run: int = 0

    def record(self, lateness_ns: int, exec_ns: int, missed: bool) -> None:
        self.lateness.add(lateness_ns)
        self.execution.add(exec_ns)
        if missed:
            self.misses += 1
            self._run += 1
            self.longest_miss_run = max(self.longest_miss_run, self._run)
        else:
            self._run = 0

    @property
    def cycles(self) -> int:
        return self.execution.total

    def summary(self) -> dict:
        n = self.cycles
        return {
            "cycles": n,
            "period_us": self.period_ns / 1e3,
            "misses": self.misses,
            "misses_per_million": (self.misses / n * 1e6) if n else 0.0,
            "longest_miss_run": self.longest_miss_run,
            "lateness": self.lateness.to_dict(),
            "execution": self.execution.to_dict(),
        }


class AbsoluteDeadlineTimer:
    """Wakes at t0 + k * period on ``clock`` (``services.runtime.bus``: CLOCK_MONOTONIC by
    default, a fake one in tests)."""

    def __init__(self, period_ns: int, clock=None):
        self.period_ns = period_ns
        self.clock = clock or MonotonicClock()
        self.next_deadline = self.clock.now_ns() + period_ns

    def wait(self) -> tuple[int, int]:
        """Sleep until the next deadline; returns (deadline, wake time)."""
        deadline = self.next_deadline
        now = self.clock.now_ns()
        if deadline > now:
            self.clock.sleep((deadline - now) / 1e9)
        wake = self.clock.now_ns()
        self.next_deadline = deadline + self.period_ns
        if wake >= self.next_deadline:
            # overran by whole periods: drop them instead of bursting to catch up
            skipped = (wake - deadline) // self.period_ns
            self.next_deadline = deadline + (skipped + 1) * self.period_ns
        return deadline, wake


class Sections:
    """Where a loop's cycles spend their time: per named section, the total and the
    longest, from time.perf_counter_ns marks (about 0.1 us each)."""

    def __init__(self, *names: str):
        self.total = dict.fromkeys(names, 0)
        self.longest = dict.fromkeys(names, 0)
        self.cycles = 0

    def add(self, name: str, ns: int) -> None:
        self.total[name] += ns
        if ns > self.longest[name]:
            self.longest[name] = ns

    def summary(self) -> dict:
        n = max(self.cycles, 1)
        return {name: {"mean_us": self.total[name] / n / 1e3, "max_us": self.longest[name] / 1e3}
                for name in self.total}
