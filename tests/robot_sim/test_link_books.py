"""The FRI link's books as the kernels keep them (robot_sim.krc.link_books): exact figures
whether a window's latencies are small (int64 sums, compiled) or not (Python integers)."""

import math

import numpy as np
import pytest

from robot_sim.krc import link_books as lb
from robot_sim.krc.link import FriConfig, FriLink
from robot_sim.krc.packets import CommandPacket, ControlMode, FriQuality

CYCLE = 1_000_000
Q, POSE, FT = np.zeros(7), np.array([1.0, 0, 0, 0.5, 0, 1, 0, 0.1, 0, 0, 1, 0.3]), np.zeros(6)


def answer(seq: int) -> CommandPacket:
    return CommandPacket(seq=seq, cart_pos=POSE.copy(), cart_stiffness=np.full(6, 100.0),
                         cart_damping=np.full(6, 0.7), add_tcp_ft=np.zeros(6), requested_mode=ControlMode.CART_IMP)


def exact(window: dict, cfg: FriConfig) -> tuple:
    """The figures and the quality of ``window`` (seq -> (missed, latency or None)) in Python
    integers, summed from scratch."""
    latencies = [lat for _, lat in window.values() if lat is not None]
    n, misses = len(window), sum(missed for missed, _ in window.values())
    total, squares = sum(latencies), sum(x * x for x in latencies)
    figures = lb.window_figures(n, misses, len(latencies), total, squares)
    quality = lb.window_quality(n, misses, len(latencies), total, squares, cfg.cycle_ns,
                                cfg.perfect_max_latency_cycles, cfg.perfect_max_jitter_cycles,
                                cfg.ok_max_miss_rate, cfg.bad_max_miss_rate)
    return figures, quality


@pytest.mark.parametrize("window", [1, 7, 100])
def test_the_figures_stay_exact_with_large_latencies_in_the_window_and_after_they_leave(window):
    """In-time answers just under the deadline (large for a window of 100: over 0.949 ms) and
    late answers seconds after their cycle closed, among small ones: every cycle's figures
    and quality are the exact ones, and once the large ones have left the window the books
    are back to their int64 sums."""
    rng = np.random.default_rng(window)
    cfg = FriConfig(window=window)
    link = FriLink(cfg)
    link.start(0)
    small = lb.small_latency(window)
    closed: dict = {}  # the reference window: seq -> (missed, latency)
    t = 0
    large_seen = 0
    for k in range(600):
        m = link.measurement(t, Q, POSE, FT)
        kind = rng.random()
        lat = None
        if k < 400 and kind < 0.1 and small + 1 < CYCLE:
            lat = int(rng.integers(small + 1, CYCLE))  # in time, large (a window of 100)
        elif kind < 0.9:
            lat = int(rng.integers(10_000, min(small, CYCLE - 1)))
        if lat is not None:
            assert link.receive(answer(m.seq), t + lat)
        out = link.end_cycle(t + CYCLE)
        assert out.answered == (lat is not None)
        closed[m.seq] = (lat is None, lat)
        if k < 400 and lat is None and rng.random() < 0.5:  # answered seconds late, after its cycle closed
            late = int(rng.integers(CYCLE, 10**10))
            assert not link.receive(answer(m.seq), t + late)
            closed[m.seq] = (True, late)
        while len(closed) > window:
            del closed[min(closed)]
        large_seen += int(link._books[lb.LARGE] > 0)
        figures, quality = exact(closed, cfg)
        s = link.statistics()
        assert (s.answer_rate, s.miss_rate, s.latency_s, s.jitter_s) == figures, k
        assert out.quality == FriQuality(quality), k
        t += CYCLE
    assert large_seen > 10  # the exact path was taken ...
    assert link._books[lb.LARGE] == 0  # ... and left: the last 200 cycles had only small latencies


def test_the_compiled_formulas_are_the_python_ones_on_small_sums():
    rng = np.random.default_rng(5)
    for _ in range(2000):
        w = int(rng.integers(1, 200))
        n = int(rng.integers(0, w + 1))
        misses = int(rng.integers(0, n + 1))
        # every answered cycle has a latency, a missed one may (a late answer)
        latencies = rng.integers(0, lb.small_latency(w) + 1, size=int(rng.integers(n - misses, n + 1))).tolist()
        args = (n, misses, len(latencies), sum(latencies), sum(x * x for x in latencies))
        assert lb._figures_small(*args) == lb.window_figures(*args)
        thresholds = (float(rng.uniform(0.01, 2)), float(rng.uniform(0.01, 2)), 0.02, 0.1)
        assert lb._quality_small(*args, CYCLE, *thresholds) == lb.window_quality(*args, CYCLE, *thresholds)


def test_small_latency_keeps_every_product_of_the_formulas_exact():
    for w in (1, 2, 100, 1000, 10**6):
        s = lb.small_latency(w)
        assert w * w * s * s < 2**53 <= w * w * (s + 1) * (s + 1)
    assert lb.small_latency(100) == 949_062 == math.isqrt((2**53 - 1) // 10_000)
