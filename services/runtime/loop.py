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
import time
from dataclasses import dataclass, field

import numpy as np


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
    period_ns: int
    lateness_ns: list = field(default_factory=list)
    exec_ns: list = field(default_factory=list)
    misses: int = 0
    longest_miss_run: int = 0
    _run: int = 0

    def record(self, lateness_ns: int, exec_ns: int, missed: bool) -> None:
        self.lateness_ns.append(lateness_ns)
        self.exec_ns.append(exec_ns)
        if missed:
            self.misses += 1
            self._run += 1
            self.longest_miss_run = max(self.longest_miss_run, self._run)
        else:
            self._run = 0

    @property
    def cycles(self) -> int:
        return len(self.exec_ns)

    def summary(self) -> dict:
        def pct(values):
            if not values:
                return {}
            a = np.asarray(values, dtype=np.float64) / 1e3
            return {"p50_us": float(np.percentile(a, 50)), "p99_us": float(np.percentile(a, 99)),
                    "p99_9_us": float(np.percentile(a, 99.9)), "max_us": float(a.max())}
        n = self.cycles
        return {
            "cycles": n,
            "period_us": self.period_ns / 1e3,
            "misses": self.misses,
            "misses_per_million": (self.misses / n * 1e6) if n else 0.0,
            "longest_miss_run": self.longest_miss_run,
            "lateness": pct(self.lateness_ns),
            "execution": pct(self.exec_ns),
        }


class AbsoluteDeadlineTimer:
    """Wakes at t0 + k * period (CLOCK_MONOTONIC)."""

    def __init__(self, period_ns: int):
        self.period_ns = period_ns
        self.next_deadline = time.monotonic_ns() + period_ns

    def wait(self) -> tuple[int, int]:
        """Sleep until the next deadline; returns (deadline, wake time)."""
        deadline = self.next_deadline
        now = time.monotonic_ns()
        if deadline > now:
            time.sleep((deadline - now) / 1e9)
        wake = time.monotonic_ns()
        self.next_deadline = deadline + self.period_ns
        if wake >= self.next_deadline:
            # overran by whole periods: drop them instead of bursting to catch up
            skipped = (wake - deadline) // self.period_ns
            self.next_deadline = deadline + (skipped + 1) * self.period_ns
        return deadline, wake
