"""Timing statistics on synthetic timestamps."""

import numpy as np
import pytest

from services.runtime.bus import FakeClock
from services.runtime.loop import AbsoluteDeadlineTimer, LoopTiming
from services.runtime.timing import Histogram, SequenceTracker, longest_run, percentiles


def test_percentiles_are_exact_and_in_microseconds():
    values = np.arange(1, 1001) * 1000  # 1..1000 us
    p = percentiles(values)
    assert p["count"] == 1000
    assert p["p50_us"] == pytest.approx(500.5)
    assert p["p99_us"] == pytest.approx(990.01)
    assert p["p99_9_us"] == pytest.approx(999.001)
    assert p["max_us"] == 1000.0 and p["min_us"] == 1.0
    assert percentiles([]) == {}


def test_histogram_bins_overflow_and_text():
    h = Histogram(limit_ns=100_000)  # 10 bins of 10 us, then overflow
    for v in (0, 9_999, 10_000, 55_000, 99_999, 100_000, 3_000_000, -5):
        h.add(v)
    assert h.counts.tolist() == [3, 1, 0, 0, 0, 1, 0, 0, 0, 1]  # -5 clamps to 0
    assert h.overflow == 2 and h.total == 8
    assert h.summary()["max_us"] == 3000.0
    text = h.text("robot loop lateness")
    assert "000000 000000003" in text and "000050 000000001" in text
    assert "# Histogram Overflows: 00002" in text and "# Total: 000000008" in text
    with pytest.raises(ValueError, match="whole number"):
        Histogram(limit_ns=15_000)


def test_longest_run_of_consecutive_misses():
    assert longest_run([]) == 0
    assert longest_run([False, True, True, False, True, True, True, False]) == 3
    timing = LoopTiming(1_000_000)
    for missed in (False, True, False, True, True, True, True, False, True):
        timing.record(0, 500_000, missed)
    s = timing.summary()
    assert s["misses"] == 6 and s["longest_miss_run"] == 4
    assert s["misses_per_million"] == pytest.approx(6 / 9 * 1e6)


def test_sequence_tracker_counts_loss_reordering_and_duplicates():
    t = SequenceTracker()
    for seq in [1, 2, 3, 5, 6, 4, 9, 9, 10]:
        t.add(seq)
    # 4 came late (out of order but not lost); 7 and 8 never came; 9 twice
    assert t.to_dict() == {"received": 9, "lost": 2, "out_of_order": 1, "duplicates": 1, "segments": 1}
    assert SequenceTracker().lost == 0
    # every tenth cycle, a gap of one message, then a new episode far later
    e = SequenceTracker(stride=10, max_gap=100)
    for seq in [10, 20, 30, 50, 60, 5000, 5010]:
        e.add(seq)
    assert (e.lost, e.segments, e.out_of_order) == (1, 2, 0)


def test_absolute_deadline_timer_skips_overruns_instead_of_bursting():
    clock = FakeClock()
    timer = AbsoluteDeadlineTimer(2_000_000, clock)  # 2 ms
    assert timer.wait() == (2_000_000, 2_000_000)  # slept to its first deadline
    clock.advance(7_100_000)  # overrun by more than three periods
    d1, w1 = timer.wait()
    assert (d1, w1) == (4_000_000, 9_100_000)  # late: no sleep
    # the next deadline after the stall is in the future, not one of the missed ones
    assert timer.next_deadline == 10_000_000 > w1
    assert timer.wait() == (10_000_000, 10_000_000)


def test_a_long_histogram_keeps_bounded_memory_and_percentiles_within_half_a_microsecond():
    from services.runtime.timing import EXACT_SAMPLES

    rng = np.random.default_rng(0)
    values = np.concatenate([rng.gamma(4.0, 70_000.0, size=3 * EXACT_SAMPLES),  # ~280 us, a long tail
                             rng.uniform(5_000_000, 9_000_000, size=200)]).astype(np.int64)  # overflow
    rng.shuffle(values)
    h = Histogram()
    for v in values:
        h.add(int(v))
    assert h.samples is None  # past EXACT_SAMPLES the samples are let go
    exact, approx = percentiles(values), h.summary()
    for k in ("p50_us", "p99_us", "p99_9_us"):
        assert abs(approx[k] - exact[k]) <= 0.5 + 1e-9, (k, approx[k], exact[k])
    for k in ("max_us", "min_us", "mean_us", "count"):
        assert approx[k] == pytest.approx(exact[k]), k
    assert approx["overflow"] == 200 and h.total == values.size
