"""Timing statistics, the way real-time engineers read them.

- ``Histogram``: 10 us bins up to a limit plus an overflow bin, printed the
  way cyclictest prints its histogram; exact percentiles from the samples.
- ``longest_run``: the longest run of consecutive misses (FRI drops out on
  consecutive misses, not on their total).
- ``SequenceTracker``: lost, out-of-order and duplicated messages of a link,
  judged from the sequence numbers the publisher stamped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

BIN_NS = 10_000  # 10 us
DEFAULT_LIMIT_NS = 5_000_000  # 5 ms: everything above lands in the overflow bin


def percentiles(values_ns) -> dict:
    """p50 / p99 / p99.9 / max in microseconds (empty: {})."""
    a = np.asarray(values_ns, dtype=np.float64)
    if a.size == 0:
        return {}
    p50, p99, p999 = np.percentile(a, (50, 99, 99.9)) / 1e3  # one sort for the three
    return {"count": int(a.size), "p50_us": float(p50), "p99_us": float(p99), "p99_9_us": float(p999),
            "max_us": float(a.max() / 1e3), "min_us": float(a.min() / 1e3), "mean_us": float(a.mean() / 1e3)}


def longest_run(flags) -> int:
    """Length of the longest run of True in a sequence of booleans."""
    best = run = 0
    for f in flags:
        run = run + 1 if f else 0
        best = max(best, run)
    return best


@dataclass
class Histogram:
    """Counts of non-negative durations in BIN_NS bins below ``limit_ns``, plus overflow."""

    limit_ns: int = DEFAULT_LIMIT_NS
    bin_ns: int = BIN_NS
    counts: np.ndarray = field(default=None)
    overflow: int = 0
    samples: list = field(default_factory=list)

    def __post_init__(self):
        if self.limit_ns % self.bin_ns:
            raise ValueError(f"limit {self.limit_ns} ns is not a whole number of {self.bin_ns} ns bins")
        if self.counts is None:
            self.counts = np.zeros(self.limit_ns // self.bin_ns, dtype=np.int64)

    def add(self, value_ns: int) -> None:
        v = max(int(value_ns), 0)  # a clock can step backwards by a hair across cores
        self.samples.append(v)
        if v >= self.limit_ns:
            self.overflow += 1
        else:
            self.counts[v // self.bin_ns] += 1

    @property
    def total(self) -> int:
        return int(self.counts.sum()) + self.overflow

    def summary(self) -> dict:
        return dict(percentiles(self.samples), overflow=self.overflow, bin_us=self.bin_ns / 1e3,
                    limit_us=self.limit_ns / 1e3)

    def to_dict(self) -> dict:
        nz = np.flatnonzero(self.counts)
        return dict(self.summary(), bins={int(i * self.bin_ns // 1000): int(self.counts[i]) for i in nz})

    def text(self, title: str = "") -> str:
        """cyclictest-style: one line per non-empty bin ("<us> <count>"), then totals."""
        lines = [f"# {title}" if title else "# histogram", f"# bin width {self.bin_ns / 1e3:.0f} us"]
        for i in np.flatnonzero(self.counts):
            lines.append(f"{i * self.bin_ns // 1000:06d} {int(self.counts[i]):09d}")
        s = self.summary()
        lines.append(f"# Total: {self.total:09d}")
        if s.get("count"):
            lines.append(f"# Min Latencies: {s['min_us']:.0f}")
            lines.append(f"# Avg Latencies: {s['mean_us']:.0f}")
            lines.append(f"# Max Latencies: {s['max_us']:.0f}")
        lines.append(f"# Histogram Overflows: {self.overflow:05d}  (>= {self.limit_ns / 1e3:.0f} us)")
        return "\n".join(lines) + "\n"


# what SequenceTracker.add says a message is
FRESH, DUPLICATE, STALE = "fresh", "duplicate", "stale"


@dataclass
class SequenceTracker:
    """Lost / out-of-order / duplicate messages of one link from its sequence numbers.

    ``stride``: the step between consecutive sequence numbers on this link (the
    estimator publishes every tenth robot cycle).  A gap of more than
    ``max_gap`` strides starts a new segment (the next episode) rather than
    counting as loss.  A message older than the newest seen is out of order and
    fills its gap: it is not lost after all.
    """

    stride: int = 1
    max_gap: int = 100
    highest: int | None = None
    received: int = 0
    out_of_order: int = 0
    duplicates: int = 0
    segments: int = 0
    _lost: int = 0
    _seen: set = field(default_factory=set)

    def add(self, seq: int) -> str:
        """Count one message; says what it is: ``FRESH`` (the newest so far: what a
        receiver may act on), ``DUPLICATE`` (a seq already seen) or ``STALE`` (older
        than the newest seen)."""
        self.received += 1
        if seq in self._seen:
            self.duplicates += 1
            return DUPLICATE
        self._seen.add(seq)
        if len(self._seen) > 200_000:  # bounded memory: duplicates older than this go unnoticed
            self._seen = {x for x in self._seen if x > seq - 100_000 * self.stride}
        if self.highest is None:
            self.highest = seq
            self.segments = 1
            return FRESH
        if seq < self.highest:
            self.out_of_order += 1
            self._lost = max(0, self._lost - 1)
            return STALE
        missing = (seq - self.highest) // self.stride - 1
        if missing > self.max_gap:
            self.segments += 1
        elif missing > 0:
            self._lost += missing
        self.highest = seq
        return FRESH

    def resync(self, seq: int) -> None:
        """Take ``seq`` as the newest from now on (a new segment): the newest seen so
        far was not part of this link's stream (a message forged far ahead)."""
        self.highest = seq
        self.segments += 1

    @property
    def lost(self) -> int:
        return self._lost

    def to_dict(self) -> dict:
        return {"received": self.received, "lost": self.lost, "out_of_order": self.out_of_order,
                "duplicates": self.duplicates, "segments": self.segments}
