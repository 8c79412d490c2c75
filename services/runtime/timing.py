"""Timing statistics, the way real-time engineers read them.

- ``Histogram``: 10 us bins up to a limit plus an overflow bin, printed the
  way cyclictest prints its histogram; exact percentiles from the samples.
- ``longest_run``: the longest run of consecutive misses (FRI drops out on
  consecutive misses, not on their total).
- ``SequenceTracker``: lost, out-of-order and duplicated messages of a link,
  judged from the sequence numbers the publisher stamped.
- ``on_the_clock``: whether a publish stamp can be a latency's start on the receiver's
  clock; one that cannot (a foreign peer's clock, a process paused for a minute) is
  counted apart, not put among the latencies.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

BIN_NS = 10_000  # 10 us
DEFAULT_LIMIT_NS = 5_000_000  # 5 ms: everything above lands in the overflow bin
# the longest a message may take and still count as a latency: past it (or negative) its
# publish stamp is not on the receiver's clock: a foreign peer stamping sent_ns 1 once
# made a robot/command "latency" of 78 679 s, the report's maximum
OFF_CLOCK_NS = 60 * 10**9


def on_the_clock(latency_ns: int) -> bool:
    """A receive time minus a publish stamp that can be a one-way latency (0 .. 60 s)."""
    return 0 <= latency_ns <= OFF_CLOCK_NS


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


# a histogram keeps its samples, for exact percentiles, up to this many; past it (a long
# episode, a link's whole run: a 10-minute soak grew the robot by 110 MiB) the
# percentiles come from 1 us bins (within 0.5 us) and the overflow's own values
EXACT_SAMPLES = 20_000
FINE_NS = 1_000
MAX_OVERFLOW_VALUES = 20_000
_PENDING = 1024  # values a histogram takes before it counts them into its bins


@dataclass
class Histogram:
    """Counts of non-negative durations in BIN_NS bins below ``limit_ns``, plus overflow.
    Memory is bounded: see EXACT_SAMPLES."""

    limit_ns: int = DEFAULT_LIMIT_NS
    bin_ns: int = BIN_NS

    def __post_init__(self):
        if self.limit_ns % self.bin_ns:
            raise ValueError(f"limit {self.limit_ns} ns is not a whole number of {self.bin_ns} ns bins")
        self._counts = np.zeros(self.limit_ns // self.bin_ns, dtype=np.int64)
        self._fine = np.zeros(-(-self.limit_ns // FINE_NS), dtype=np.int64)
        # the values not yet counted: counted in bulk (``_flush``), since counting each as it came
        # (its bins, sum, extremes) cost a 1 kHz loop about half a microsecond per value
        self._pending: list = []
        self._over: list = []  # the overflow's values (the largest kept past MAX_OVERFLOW_VALUES)
        self._overflow = 0
        self._samples: list | None = []  # None once past EXACT_SAMPLES
        self._n = 0
        self._sum = 0
        self._min = None
        self._max = 0

    def add(self, value_ns: int) -> None:
        # a loop adds several values a cycle: each is only queued here, and counted with the
        # others in bulk (``_flush``), in the order they came
        self._pending.append(int(value_ns))
        if len(self._pending) >= _PENDING:
            self._flush()

    @property
    def counts(self) -> np.ndarray:
        """The count of each bin below the limit (the array itself: a caller may add to it)."""
        self._flush()
        return self._counts

    @property
    def overflow(self) -> int:
        """How many values were at or past the limit (a caller may add to it)."""
        self._flush()
        return self._overflow

    @overflow.setter
    def overflow(self, n: int) -> None:
        self._flush()
        self._overflow = n

    @property
    def samples(self) -> list | None:
        """Every value, for exact percentiles; None once past EXACT_SAMPLES."""
        self._flush()
        return self._samples

    def _flush(self) -> None:
        """Count the queued values: their sum, extremes and exact samples, the overflow's
        values, the bins and the 1 us bins (whatever reads them calls this first)."""
        if not self._pending:
            return
        values = np.asarray(self._pending, dtype=np.int64)
        self._pending = []
        np.maximum(values, 0, out=values)  # a clock can step backwards by a hair across cores
        self._n += values.size
        self._sum += int(values.sum())
        low, high = int(values.min()), int(values.max())
        self._max = max(self._max, high)
        self._min = low if self._min is None else min(self._min, low)
        if self._samples is not None:
            self._samples.extend(values.tolist())
            if len(self._samples) > EXACT_SAMPLES:
                self._samples = None
        if high >= self.limit_ns:
            over = values >= self.limit_ns
            for v in values[over].tolist():  # rare: one by one, as they came, the largest kept
                self._overflow += 1
                self._over.append(v)
                if len(self._over) > 2 * MAX_OVERFLOW_VALUES:
                    self._over = sorted(self._over)[-MAX_OVERFLOW_VALUES:]
            values = values[~over]
        self._counts += np.bincount(values // self.bin_ns, minlength=self._counts.size)
        self._fine += np.bincount(values // FINE_NS, minlength=self._fine.size)

    def _percentiles(self) -> dict:
        """percentiles() from the 1 us bins (bin centres, linearly between ranks) and the
        overflow's values, for a histogram past EXACT_SAMPLES."""
        self._flush()
        n = self._n
        fine = self._fine
        cum = np.cumsum(fine)
        over = np.sort(np.asarray(self._over, dtype=np.float64))
        below = int(cum[-1]) if cum.size else 0

        def value(rank: int) -> float:
            if rank < below:
                return (int(np.searchsorted(cum, rank, side="right")) + 0.5) * FINE_NS
            i = rank - below - (self.overflow - over.size)  # the smallest overflow values may be gone
            return float(over[min(max(i, 0), over.size - 1)]) if over.size else float(self.limit_ns)

        out = {}
        for name, q in (("p50_us", 50), ("p99_us", 99), ("p99_9_us", 99.9)):
            r = q / 100 * (n - 1)
            lo = int(np.floor(r))
            hi = min(lo + 1, n - 1)
            out[name] = (value(lo) + (r - lo) * (value(hi) - value(lo))) / 1e3
        return {"count": n, **out, "max_us": self._max / 1e3, "min_us": self._min / 1e3,
                "mean_us": self._sum / n / 1e3}

    @property
    def total(self) -> int:
        return int(self.counts.sum()) + self.overflow

    def summary(self) -> dict:
        self._flush()
        exact = percentiles(self.samples) if self.samples is not None else self._percentiles()
        return dict(exact, overflow=self.overflow, bin_us=self.bin_ns / 1e3, limit_us=self.limit_ns / 1e3)

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
        if len(self._seen) > 20_000:  # bounded memory: a copy older than this counts as stale, not duplicate
            self._seen = {x for x in self._seen if x > seq - 10_000 * self.stride}
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
