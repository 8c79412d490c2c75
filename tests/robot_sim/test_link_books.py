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


def test_an_answer_given_as_numbers_fares_as_the_packet_they_make():
    """``receive_fields`` (a robot/command message's numbers, straight into the link's slot)
    against ``receive`` of the packet they make, link beside link: answers in time, late,
    twice, for cycles never sent or long gone, with a negative or huge seq, numbers out of
    range or not a rotation, other modes; the same verdicts and reasons, the same outcomes
    and statistics, the same packets when asked for."""
    rng = np.random.default_rng(12)
    links = [FriLink(FriConfig(perfect_hold_cycles=20)) for _ in range(2)]
    for link in links:
        link.start(0)
        link.request_command_mode()
    t, bad_pose, applied = 0, POSE.copy(), 0
    bad_pose[0] = 1.5
    for k in range(3000):
        ms = [link.measurement(t, Q, POSE, FT) for link in links]
        # first the link reaches CMD; then, now and then, after the cycle's answer (or none) anything
        chaos = k > 600 and rng.random() < 0.2
        for n in range(2 if chaos else 1):
            chaos = chaos and (n == 1 or rng.random() < 0.3)
            seq = int(rng.choice([ms[0].seq, ms[0].seq - 3, ms[0].seq + 2, -4, 2**63 + 5])) if chaos else ms[0].seq
            mode = int(rng.choice([2, 0, 1, 3])) if chaos else 2
            pose = bad_pose if chaos and rng.random() < 0.2 else POSE
            stiffness = np.array([100.0, 1e9] + [100.0] * 4) if chaos and rng.random() < 0.2 else np.full(6, 100.0)
            add = np.array([float(k), 0.0, 0.0, 0.5, 0.0, 0.0])
            arrival = t + (int(rng.choice([100_000, 900_000, 1_200_000])) if chaos else 100_000)
            verdicts = [links[0].receive(CommandPacket(seq, pose.copy(), stiffness.copy(), np.full(6, 0.7), add.copy(),
                                                       requested_mode=ControlMode(mode)), arrival, owned=True),
                        links[1].receive_fields(seq, mode, pose.tolist(), stiffness.tolist(), [0.7] * 6, add.tolist(),
                                                arrival)]
            assert verdicts[0] == verdicts[1] and links[0].last_reject_reason == links[1].last_reject_reason, k
        outs = [link.end_cycle(t + CYCLE) for link in links]
        a, b = outs
        assert (a.seq, a.answered, a.bridged, a.hold, a.state, a.quality) == \
            (b.seq, b.answered, b.bridged, b.hold, b.state, b.quality), k
        assert (a.command is None) == (b.command is None), k
        if a.command is not None:
            applied += 1
            assert a.command.add_tcp_ft.tobytes() == b.command.add_tcp_ft.tobytes()
            assert a.command.requested_mode == b.command.requested_mode and a.command.seq == b.command.seq
        assert links[0].statistics() == links[1].statistics(), k
        t += CYCLE
    s = links[0].statistics()
    assert s.corrupt > 50 and s.late > 10 and s.duplicate > 20 and s.bridged >= 1 and applied > 500, (s, applied)
    # a mode FRI does not have (a foreign peer's command): refused and counted, as a packet's
    assert not links[1].receive_fields(ms[1].seq, 7, POSE.tolist(), [100.0] * 6, [0.7] * 6, [0.0] * 6, t)
    assert links[1].last_reject_reason == "requested_mode is not a ControlMode (7)"
