"""The KRC side of the FRI 1.0 link, driven with synthetic times (no clock, no network)."""

from dataclasses import replace

import numpy as np
import pytest

from robot_sim.krc.faults import LinkFaults
from robot_sim.krc.link import FriConfig, FriLink
from robot_sim.krc.packets import CommandPacket, ControlMode, FriQuality, FriState, command_problem

CYCLE = 1_000_000
Q = np.linspace(-0.3, 0.3, 7)
POSE = np.array([1.0, 0, 0, 0.5, 0, 1, 0, 0.1, 0, 0, 1, 0.3])
FT = np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])  # Fx Fy Fz Tz Ty Tx
STIFF = np.array([1000.0, 1000.0, 1000.0, 100.0, 100.0, 100.0])


def answer(m, **kw) -> CommandPacket:
    """A valid answer to ``m``, marked (add_tcp_ft[0] = seq) so tests can tell answers apart."""
    cmd = CommandPacket.from_measurement(m, cart_stiffness=STIFF, **kw)
    cmd.add_tcp_ft[0] = m.seq
    return cmd


class Bench:
    """Drives one link cycle by cycle at t = k * cycle."""

    def __init__(self, link: FriLink | None = None, t0: int = 0):
        self.link = link if link is not None else FriLink()
        self.t = t0
        self.link.start(t0)

    def cycle(self, latency: int | None = 200_000, packet_fn=None):
        """One cycle; the answer arrives ``latency`` after the measurement (None: no answer)."""
        link = self.link
        m = link.measurement(self.t, Q, POSE, FT)
        if latency is not None:
            link.receive(packet_fn(m) if packet_fn else answer(m), self.t + latency)
        out = link.end_cycle(self.t + link.config.cycle_ns)
        self.t += link.config.cycle_ns
        return m, out

    def run(self, n: int, **kw):
        return [self.cycle(**kw)[1] for _ in range(n)]

    def to_cmd(self):
        self.link.request_command_mode()
        for _ in range(10 * self.link.config.perfect_hold_cycles):
            if self.cycle()[1].state == FriState.CMD:
                return
        raise AssertionError("never reached CMD")


# ------------------------------------------------------------------ configuration
@pytest.mark.parametrize(
    "field, value",
    [
        ("cycle_ns", 0),
        ("cycle_ns", 999_999),
        ("cycle_ns", 100_000_001),
        ("cycle_ns", 1e6),
        ("cycle_ns", True),
        ("window", 0),
        ("perfect_hold_cycles", 0),
        ("max_bridged_misses", -1),
        ("bad_max_miss_rate", 1.5),
        ("perfect_max_jitter_cycles", 0.0),
    ],
)
def test_bad_configuration_names_field_and_value(field, value):
    with pytest.raises(ValueError, match=rf"FriConfig\.{field} = {value!r}"):
        FriConfig(**{field: value})


def test_miss_rate_thresholds_must_be_ordered():
    with pytest.raises(ValueError, match="ok_max_miss_rate.*bad_max_miss_rate"):
        FriConfig(ok_max_miss_rate=0.2, bad_max_miss_rate=0.1)


def test_cycle_limits_are_inclusive():
    assert FriConfig(cycle_ns=1_000_000).cycle_ns == 1_000_000
    assert FriConfig(cycle_ns=100_000_000).cycle_ns == 100_000_000


# ------------------------------------------------------------ sequence numbers
def test_sequence_numbers_and_reflected_seq():
    b = Bench()
    link = b.link
    m1, out1 = b.cycle()
    assert (m1.seq, m1.reflected_seq, m1.stamp_ns) == (1, -1, 0)
    assert out1.seq == 1 and out1.answered
    m2, _ = b.cycle(latency=None)  # missed: nothing received
    assert (m2.seq, m2.reflected_seq) == (2, 1)
    m3 = link.measurement(b.t, Q, POSE, FT)
    assert (m3.seq, m3.reflected_seq) == (3, 1)
    # An answer arriving after the deadline is still a packet the KRC received.
    assert not link.receive(answer(m3), b.t + CYCLE + 1)
    link.end_cycle(b.t + CYCLE)
    b.t += CYCLE
    m4 = link.measurement(b.t, Q, POSE, FT)
    assert (m4.seq, m4.reflected_seq) == (4, 3)
    # A corrupt packet tells the KRC nothing.
    bad = answer(m4)
    bad.cart_damping[0] = np.nan
    assert not link.receive(bad, b.t + 100)
    link.end_cycle(b.t + CYCLE)
    b.t += CYCLE
    assert link.measurement(b.t, Q, POSE, FT).reflected_seq == 3


def test_seq_survives_restart_and_stale_answers_are_late():
    b = Bench()
    b.run(5)
    link = b.link
    m_old = link.measurement(b.t, Q, POSE, FT)
    link.stop()
    assert link.state == FriState.OFF
    assert not link.receive(answer(m_old), b.t + 10)  # nothing to answer while OFF
    link.start(b.t + 10 * CYCLE)
    b.t += 10 * CYCLE
    s = link.statistics()
    assert (s.sent, s.answered, s.missed, s.window_packets) == (0, 0, 0, 0)
    m = link.measurement(b.t, Q, POSE, FT)
    assert m.seq == m_old.seq + 1 and m.reflected_seq == -1
    assert m.quality == FriQuality.UNACCEPTABLE  # nothing known about the new session yet
    assert not link.receive(answer(m_old), b.t + 10)
    assert link.statistics().late == 1
    assert link.receive(answer(m), b.t + 20)


def test_measurement_copies_its_arrays_and_keeps_fri_wrench_order():
    link = FriLink()
    link.start(0)
    q, x, ft = Q.copy(), POSE.copy(), FT.copy()
    m = link.measurement(0, q, x, ft)
    q[:] = x[:] = ft[:] = 99.0
    np.testing.assert_array_equal(m.msr_jnt_pos, Q)
    np.testing.assert_array_equal(m.msr_cart_pos, POSE)
    np.testing.assert_array_equal(m.est_ext_tcp_ft, FT)
    assert m.msr_cart_pos.dtype == np.float64 and m.control_mode == ControlMode.CART_IMP


def test_receive_keeps_its_own_copy_of_the_command():
    b = Bench()
    b.to_cmd()
    link = b.link
    m = link.measurement(b.t, Q, POSE, FT)
    cmd = answer(m)
    assert link.receive(cmd, b.t + 100)
    cmd.cart_stiffness[:] = 0.0  # the remote reuses its buffer; the wire would not share it
    out = link.end_cycle(b.t + CYCLE)
    assert out.command is not cmd
    np.testing.assert_array_equal(out.command.cart_stiffness, STIFF)


def test_receive_keeps_an_owned_command_without_copying_it():
    """owned: the caller made the packet for the link (the robot node, from a message's
    lists), so the link keeps that very packet; a copy would be the same numbers."""
    b = Bench()
    b.to_cmd()
    link = b.link
    m = link.measurement(b.t, Q, POSE, FT)
    cmd = answer(m)
    assert link.receive(cmd, b.t + 100, owned=True)
    assert link.end_cycle(b.t + CYCLE).command is cmd


# --------------------------------------------------------------- state machine
def test_mon_to_cmd_only_after_request_and_perfect_hold():
    b = Bench()
    hold = b.link.config.perfect_hold_cycles
    assert b.link.request_command_mode()
    for k in range(hold - 1):
        _, out = b.cycle()
        assert out.quality == FriQuality.PERFECT
        assert out.state == FriState.MON, f"CMD entered after {k + 1} PERFECT cycles"
        assert out.hold and out.command is None and not out.bridged
    _, out = b.cycle()
    assert out.state == FriState.CMD and b.link.state == FriState.CMD
    # The cycle that enters CMD applies its own answer.
    assert not out.hold and out.command is not None and out.command.add_tcp_ft[0] == out.seq


def test_perfect_link_without_request_stays_in_monitor_mode():
    b = Bench()
    hold = b.link.config.perfect_hold_cycles
    outs = b.run(hold + 100)
    assert all(o.state == FriState.MON and o.hold and o.command is None for o in outs)
    assert outs[-1].quality == FriQuality.PERFECT
    # The PERFECT run counts without a request: a late request takes effect at once.
    b.link.request_command_mode()
    assert b.cycle()[1].state == FriState.CMD


def test_command_requests_are_refused_when_off():
    link = FriLink()
    assert not link.request_command_mode()
    assert not link.request_monitor_mode()
    with pytest.raises(RuntimeError, match="OFF"):
        link.measurement(0, Q, POSE, FT)


def test_request_monitor_mode_leaves_cmd_and_clears_request():
    b = Bench()
    b.to_cmd()
    assert b.link.request_monitor_mode()
    assert b.link.state == FriState.MON and not b.link.command_requested
    _, out = b.cycle()
    assert out.state == FriState.MON and out.hold and out.command is None


def test_control_mode_switch_only_in_monitor_mode():
    link = FriLink()
    assert not link.switch_control_mode(ControlMode.JNT_IMP)  # OFF
    assert link.control_mode == ControlMode.CART_IMP
    b = Bench(link)
    assert link.switch_control_mode(ControlMode.JNT_IMP)
    assert link.control_mode == ControlMode.JNT_IMP
    assert link.switch_control_mode(ControlMode.CART_IMP)
    b.to_cmd()
    assert not link.switch_control_mode(ControlMode.POSITION)
    assert link.control_mode == ControlMode.CART_IMP
    link.request_monitor_mode()
    assert link.switch_control_mode(ControlMode.POSITION)
    assert b.cycle()[0].control_mode == ControlMode.POSITION
    with pytest.raises(ValueError):
        link.switch_control_mode(9)


def test_command_for_another_mode_is_held_but_not_a_miss():
    b = Bench()
    b.to_cmd()
    _, out = b.cycle(packet_fn=lambda m: answer(m, requested_mode=ControlMode.JNT_IMP))
    assert out.answered and out.hold and out.command is None and not out.bridged
    assert out.state == FriState.CMD and out.quality == FriQuality.PERFECT
    s = b.link.statistics()
    assert s.mode_mismatch == 1 and s.missed == 0


# ------------------------------------------------------ misses, bridging, hold
def test_isolated_miss_is_bridged_and_two_consecutive_misses_hold():
    b = Bench()
    b.to_cmd()
    _, applied = b.cycle()
    assert applied.command is not None and applied.command.add_tcp_ft[0] == applied.seq

    _, out = b.cycle(latency=None)
    assert out.bridged and not out.hold and out.command is applied.command
    assert out.state == FriState.CMD and out.consecutive_misses == 1

    _, fresh = b.cycle()
    assert not fresh.bridged and fresh.command.add_tcp_ft[0] == fresh.seq
    # Let the miss leave the window, so the next two are the only ones in it.
    outs = b.run(b.link.config.window)
    assert outs[-1].quality == FriQuality.PERFECT and outs[-1].state == FriState.CMD
    last = outs[-1].command

    _, out1 = b.cycle(latency=None)
    _, out2 = b.cycle(latency=None)
    assert out1.bridged and out1.command is last
    assert out2.hold and out2.command is None and not out2.bridged
    # 2 misses of 100 is still OK, so the link stays in CMD and only holds.
    assert out2.state == FriState.CMD and out2.quality == FriQuality.OK and out2.consecutive_misses == 2

    _, back = b.cycle()
    assert back.command is not None and not back.hold and back.consecutive_misses == 0
    s = b.link.statistics()
    assert (s.bridged, s.held, s.longest_miss_run) == (2, 1, 2)


def test_no_bridging_when_configured_off():
    b = Bench(FriLink(FriConfig(max_bridged_misses=0)))
    b.to_cmd()
    _, out = b.cycle(latency=None)
    assert out.hold and out.command is None and not out.bridged and out.state == FriState.CMD


def test_late_answers_are_misses_and_drop_cmd_to_mon():
    b = Bench()
    b.to_cmd()
    late = int(1.2 * CYCLE)
    _, o1 = b.cycle(latency=late)
    _, o2 = b.cycle(latency=late)
    _, o3 = b.cycle(latency=late)
    assert not o1.answered and o1.bridged and o1.state == FriState.CMD and o1.quality == FriQuality.OK
    assert o2.hold and o2.state == FriState.CMD and o2.quality == FriQuality.OK
    assert o3.quality == FriQuality.BAD and o3.state == FriState.MON
    assert o3.hold and o3.command is None
    assert not b.link.command_requested
    outs = b.run(8, latency=late)
    assert outs[-1].quality == FriQuality.UNACCEPTABLE  # 11 of 100 missed
    s = b.link.statistics()
    assert s.late == 11 and s.missed == 11 and s.longest_miss_run == 11
    assert s.miss_rate == pytest.approx(0.11) and s.answer_rate == pytest.approx(0.89)


def test_answer_exactly_at_deadline_or_for_previous_cycle_is_late():
    b = Bench()
    link = b.link
    m = link.measurement(0, Q, POSE, FT)
    assert not link.receive(answer(m), CYCLE)  # at the deadline is too late
    link.end_cycle(CYCLE)
    m2 = link.measurement(CYCLE, Q, POSE, FT)
    assert not link.receive(answer(m), CYCLE + 10)  # answers the previous cycle
    assert link.receive(answer(m2), 2 * CYCLE - 1)
    out = link.end_cycle(2 * CYCLE)
    assert out.answered
    s = link.statistics()
    assert (s.late, s.answered, s.missed) == (2, 1, 1)


def test_duplicate_answer_is_ignored_and_first_wins():
    b = Bench()
    b.to_cmd()
    link = b.link
    m = link.measurement(b.t, Q, POSE, FT)
    first, second = answer(m), answer(m)
    second.add_tcp_ft[0] = -1.0
    assert link.receive(first, b.t + 100)
    assert not link.receive(second, b.t + 200)
    out = link.end_cycle(b.t + CYCLE)
    assert out.command.add_tcp_ft[0] == m.seq
    assert link.statistics().duplicate == 1


def test_recovery_to_perfect_then_cmd_after_new_request():
    b = Bench()
    b.to_cmd()
    b.run(12, latency=None)
    assert b.link.state == FriState.MON and b.link.quality == FriQuality.UNACCEPTABLE
    assert b.link.request_command_mode()
    window, hold = b.link.config.window, b.link.config.perfect_hold_cycles
    qualities, states = [], []
    for _ in range(window + hold):
        _, out = b.cycle()
        qualities.append(out.quality)
        states.append(out.state)
    # The last miss leaves the window after `window` answered cycles.
    assert qualities[window - 2] == FriQuality.OK and qualities[window - 1] == FriQuality.PERFECT
    assert FriQuality.BAD in qualities[:window]
    first_cmd = states.index(FriState.CMD)
    assert first_cmd == window - 1 + hold - 1


def test_recovery_without_new_request_stays_in_monitor_mode():
    b = Bench()
    b.to_cmd()
    b.run(5, latency=None)
    outs = b.run(b.link.config.window + b.link.config.perfect_hold_cycles + 10)
    assert outs[-1].quality == FriQuality.PERFECT
    assert all(o.state == FriState.MON for o in outs)


# ------------------------------------------------------------------- quality
def test_quality_on_a_short_window_uses_the_packets_seen_so_far():
    b = Bench()
    assert b.cycle(latency=None)[1].quality == FriQuality.UNACCEPTABLE  # 1 of 1 missed
    b2 = Bench()
    outs = b2.run(19)
    outs.append(b2.cycle(latency=None)[1])
    assert outs[-1].quality == FriQuality.BAD  # 1 of 20 = 5 %
    outs = b2.run(40)
    assert outs[-1].quality == FriQuality.OK  # 1 of 60


def test_slow_or_jittery_answers_are_ok_not_perfect():
    slow = Bench()
    slow.link.request_command_mode()
    outs = slow.run(700, latency=int(0.6 * CYCLE))
    assert all(o.quality == FriQuality.OK and o.state == FriState.MON for o in outs)

    jittery = Bench()
    jittery.link.request_command_mode()
    outs = [jittery.cycle(latency=[50_000, 900_000][k % 2])[1] for k in range(700)]
    # mean 0.475 cycle passes, jitter 0.425 cycle does not
    assert outs[-1].quality == FriQuality.OK and outs[-1].state == FriState.MON
    s = jittery.link.statistics()
    assert s.latency_s == pytest.approx(475e-6) and s.jitter_s == pytest.approx(425e-6)


# ---------------------------------------------------------------- statistics
def test_statistics_are_exact_on_synthetic_timestamps(rng):
    b = Bench()
    link = b.link
    n = 150
    latencies = rng.integers(20_000, 900_000, size=n)
    missing = {10, 40, 41, 42, 120, 135}  # the run 40..42 is the longest
    late_in_cycle = {130: 1_300_000}  # arrives after the deadline, before end_cycle
    # Arrive after end_cycle, before the next measurement; 30 has left the window by the end.
    late_after_close = {30: 1_100_000, 140: 1_700_000}
    answered_ok = np.ones(n, dtype=bool)
    lat_seen = np.full(n, -1, dtype=np.int64)
    for k in range(n):
        t = b.t
        m = link.measurement(t, Q, POSE, FT)
        if k in late_in_cycle:
            link.receive(answer(m), t + late_in_cycle[k])
            answered_ok[k], lat_seen[k] = False, late_in_cycle[k]
        elif k in missing or k in late_after_close:
            answered_ok[k] = False
        else:
            assert link.receive(answer(m), t + int(latencies[k]))
            lat_seen[k] = latencies[k]
        link.end_cycle(t + CYCLE)
        if k in late_after_close:
            assert not link.receive(answer(m), t + late_after_close[k])
            lat_seen[k] = late_after_close[k]
        b.t += CYCLE

    s = link.statistics()
    assert (s.sent, s.answered, s.missed, s.late, s.corrupt) == (n, n - 9, 9, 3, 0)
    assert s.longest_miss_run == 3 and s.window_packets == 100
    last = slice(n - 100, n)
    assert s.answer_rate == answered_ok[last].mean()
    assert s.miss_rate == pytest.approx(1.0 - answered_ok[last].mean(), abs=1e-15)
    lat = lat_seen[last][lat_seen[last] >= 0].astype(np.float64)
    assert len(lat) == 100 - 2  # 120 and 135 never answered
    assert s.latency_s == pytest.approx(lat.mean() * 1e-9, rel=1e-12)
    assert s.jitter_s == pytest.approx(lat.std() * 1e-9, rel=1e-9)
    # The next measurement carries the same figures.
    m = link.measurement(b.t, Q, POSE, FT)
    assert (m.answer_rate, m.miss_rate, m.latency_s, m.jitter_s) == (s.answer_rate, s.miss_rate, s.latency_s, s.jitter_s)


def test_statistics_of_an_empty_window_are_zero_not_nan():
    link = FriLink()
    link.start(0)
    m = link.measurement(0, Q, POSE, FT)
    assert (m.answer_rate, m.miss_rate, m.latency_s, m.jitter_s) == (0.0, 0.0, 0.0, 0.0)
    assert link.statistics().sent == 1


# --------------------------------------------------------------- bad packets
def _good():
    link = FriLink()
    link.start(0)
    return answer(link.measurement(0, Q, POSE, FT))


def _set(name, index, value):
    def make(p):
        arr = getattr(p, name).copy()
        arr[index] = value
        return replace(p, **{name: arr})
    return make


MIRRORED = POSE.copy()
MIRRORED[8:11] *= -1.0

BAD_PACKETS = {
    "nan cart_pos": (_set("cart_pos", 3, np.nan), "cart_pos[3] is not finite"),
    "inf stiffness": (_set("cart_stiffness", 0, np.inf), "cart_stiffness[0] is not finite"),
    "nan add_tcp_ft": (_set("add_tcp_ft", 5, np.nan), "add_tcp_ft[5]"),
    "nan jnt_pos": (_set("jnt_pos", 2, np.nan), "jnt_pos[2]"),
    "cart_pos 3x4": (lambda p: replace(p, cart_pos=POSE.reshape(3, 4)), "cart_pos has shape (3, 4)"),
    "cart_pos short list": (lambda p: replace(p, cart_pos=list(POSE[:11])), "cart_pos has shape (11,)"),
    "cart_pos missing": (lambda p: replace(p, cart_pos=None), "cart_pos is missing"),
    "cart_pos text": (lambda p: replace(p, cart_pos="pose"), "cart_pos"),
    "cart_pos zeros": (lambda p: replace(p, cart_pos=np.zeros(12)), "not orthonormal"),
    "cart_pos mirrored": (lambda p: replace(p, cart_pos=MIRRORED), "determinant"),
    "stiffness dtype object": (lambda p: replace(p, cart_stiffness=np.array([1] * 6, dtype=object)), "dtype"),
    "translational stiffness 6000": (_set("cart_stiffness", 1, 6000.0), "cart_stiffness[1] = 6000.0 outside [0, 5000.0]"),
    "rotational stiffness 400": (_set("cart_stiffness", 4, 400.0), "cart_stiffness[4] = 400.0 outside [0, 300.0]"),
    "negative stiffness": (_set("cart_stiffness", 2, -1.0), "cart_stiffness[2]"),
    "damping 1.5": (_set("cart_damping", 0, 1.5), "cart_damping[0] = 1.5 outside [0, 1]"),
    "damping negative": (_set("cart_damping", 5, -0.1), "cart_damping[5]"),
    "seq text": (lambda p: replace(p, seq="1"), "seq is not an integer"),
    "seq float": (lambda p: replace(p, seq=1.0), "seq is not an integer"),
    "seq bool": (lambda p: replace(p, seq=True), "seq is not an integer"),
    "seq negative": (lambda p: replace(p, seq=-1), "seq is negative"),
    "unknown mode": (lambda p: replace(p, requested_mode=7), "requested_mode"),
    "unhashable mode": (lambda p: replace(p, requested_mode=[1]), "requested_mode"),
    "position mode without jnt_pos": (
        lambda p: replace(p, jnt_pos=None, requested_mode=ControlMode.POSITION), "jnt_pos is missing"),
    "joint stiffness 6000": (lambda p: replace(p, jnt_stiffness=np.full(7, 6000.0)),
                             "jnt_stiffness[0] = 6000.0 outside [0, 5000]"),
    "joint damping 1.5": (lambda p: replace(p, jnt_damping=np.full(7, 1.5)), "jnt_damping[0] = 1.5 outside [0, 1]"),
    "joint torque nan": (lambda p: replace(p, add_jnt_trq=np.array([0, 0, np.nan, 0, 0, 0, 0.0])),
                         "add_jnt_trq[2] is not finite"),
    "joint stiffness short": (lambda p: replace(p, jnt_stiffness=np.zeros(6)), "jnt_stiffness has shape (6,)"),
}


@pytest.mark.parametrize("case", list(BAD_PACKETS))
def test_bad_packets_are_rejected_counted_and_never_raise(case):
    make, reason = BAD_PACKETS[case]
    link = FriLink()
    link.start(0)
    m = link.measurement(0, Q, POSE, FT)
    bad = make(answer(m))
    ok, why = bad.is_valid()
    assert not ok and reason in why
    assert link.receive(bad, 100) is False
    assert reason in link.last_reject_reason
    out = link.end_cycle(CYCLE)
    assert not out.answered and out.hold
    s = link.statistics()
    assert (s.corrupt, s.missed, s.late) == (1, 1, 0)


@pytest.mark.parametrize("thing", [None, "packet", {"seq": 1}, 42])
def test_things_that_are_not_packets_are_corrupt(thing):
    link = FriLink()
    link.start(0)
    link.measurement(0, Q, POSE, FT)
    assert link.receive(thing, 100) is False
    assert link.statistics().corrupt == 1


def test_packets_for_unsent_seq_or_from_the_past_are_corrupt():
    link = FriLink()
    link.start(0)
    m = link.measurement(1000, Q, POSE, FT)
    assert not link.receive(replace(answer(m), seq=m.seq + 1), 2000)
    assert "never sent" in link.last_reject_reason
    assert not link.receive(answer(m), 999)
    assert "before measurement" in link.last_reject_reason
    assert link.statistics().corrupt == 2
    assert link.receive(answer(m), 1500)


def test_limit_values_and_plain_lists_are_valid():
    p = _good()
    p = replace(p, cart_stiffness=[5000.0, 0.0, 5000, 300.0, 0.0, 300], cart_damping=[0.0, 1.0, 0.5, 1, 0, 0.7],
                cart_pos=list(POSE), jnt_pos=None)
    assert p.is_valid() == (True, "")


# ------------------------------------------------------------ protocol misuse
def test_out_of_order_calls_are_clear_errors():
    link = FriLink()
    link.start(0)
    with pytest.raises(RuntimeError, match="no open cycle"):
        link.end_cycle(CYCLE)
    with pytest.raises(ValueError, match="shapes"):
        link.measurement(0, Q[:6], POSE, FT)
    assert link.seq == 0  # a refused measurement sends nothing
    link.measurement(0, Q, POSE, FT)
    with pytest.raises(RuntimeError, match="still open"):
        link.measurement(CYCLE, Q, POSE, FT)
    with pytest.raises(ValueError, match="before the cycle's deadline"):
        link.end_cycle(CYCLE - 1)
    link.end_cycle(CYCLE + 5)  # an overrun host loop may close late
    with pytest.raises(ValueError, match="before the previous cycle's deadline"):
        link.measurement(CYCLE - 1, Q, POSE, FT)
    with pytest.raises(RuntimeError, match="already"):
        link.start(0)


# --------------------------------------------------------------------- faults
def _faulty_run(faults: LinkFaults, n: int):
    link = FriLink(faults=faults)
    link.start(0)
    link.request_command_mode()
    trace = []
    for k in range(n):
        t = k * CYCLE
        m = link.measurement(t, Q, POSE, FT)
        seen = link.deliver_measurement(m)
        if seen is not None:
            link.deliver(answer(seen), t + 50_000)
        out = link.end_cycle(t + CYCLE)
        applied = None if out.command is None else int(out.command.add_tcp_ft[0])  # the answer's mark
        trace.append((out.answered, out.bridged, out.hold, int(out.state), int(out.quality), applied))
    return link, trace


def test_faults_with_the_same_seed_are_reproducible():
    kw = dict(delay_ns=300_000, jitter_ns=800_000, drop_probability=0.01, corrupt_probability=0.01,
              measurement_drop_probability=0.01)
    link_a, trace_a = _faulty_run(LinkFaults(seed=7, **kw), 1500)
    link_b, trace_b = _faulty_run(LinkFaults(seed=7, **kw), 1500)
    _, trace_c = _faulty_run(LinkFaults(seed=8, **kw), 1500)
    assert trace_a == trace_b
    assert link_a.statistics() == link_b.statistics()
    assert trace_a != trace_c
    assert link_a.statistics().late > 0  # some jittered answers miss the deadline


def test_dropped_and_corrupted_commands_are_about_p_and_counted():
    n = 5000
    faults = LinkFaults(seed=3, drop_probability=0.2, corrupt_probability=0.1)
    link, _ = _faulty_run(faults, n)
    s = link.statistics()
    assert 0.17 * n < faults.dropped < 0.23 * n
    assert 0.06 * n < faults.corrupted < 0.12 * n  # ~0.1 of the packets that were not dropped
    assert s.corrupt == faults.corrupted
    assert s.missed == faults.dropped + faults.corrupted
    assert s.late == 0


def test_lost_measurements_are_never_answered():
    n = 4000
    faults = LinkFaults(seed=11, measurement_drop_probability=0.1)
    link, _ = _faulty_run(faults, n)
    assert 0.07 * n < faults.measurements_dropped < 0.13 * n
    assert link.statistics().missed == faults.measurements_dropped


def test_delay_and_jitter_shift_arrival_times():
    faults = LinkFaults(seed=5, delay_ns=100_000, jitter_ns=200_000)
    link, _ = _faulty_run(faults, 300)
    s = link.statistics()
    assert s.missed == 0
    # Answers sent 50 us after the measurement arrive 150..350 us after it.
    assert 150e-6 <= s.latency_s <= 350e-6 and 0 < s.jitter_s < 100e-6

    late_link, trace = _faulty_run(LinkFaults(seed=5, delay_ns=CYCLE), 600)
    assert late_link.statistics().late == 600 and late_link.statistics().answered == 0
    assert trace[-1][3:5] == (int(FriState.MON), int(FriQuality.UNACCEPTABLE))
    assert late_link.statistics().latency_s == pytest.approx((CYCLE + 50_000) * 1e-9)


def test_corruption_does_not_touch_the_senders_packet():
    faults = LinkFaults(seed=0, corrupt_probability=1.0)
    link = FriLink(faults=faults)
    link.start(0)
    m = link.measurement(0, Q, POSE, FT)
    cmd = answer(m)
    assert not link.deliver(cmd, 10)
    assert cmd.is_valid() == (True, "")
    assert link.statistics().corrupt == 1


def test_duplicated_answers_are_rejected_and_never_applied_twice():
    n = 2000
    faults = LinkFaults(seed=4, duplicate_probability=0.3)
    link, trace = _faulty_run(faults, n)
    s = link.statistics()
    assert 0.25 * n < faults.duplicated < 0.35 * n
    # the copy comes 0..1 ms after the original, which arrives 50 us into a 1 ms cycle: a copy
    # within the deadline is a duplicate, one after it late; neither is applied
    assert s.duplicate + s.late == faults.duplicated and s.duplicate > 0 and s.late > 0
    assert s.answered == n and s.missed == 0
    clean_link, clean_trace = _faulty_run(None, n)
    assert trace == clean_trace  # what the KRC applied, cycle by cycle, is the clean run's


def test_reordered_answers_arrive_after_the_next_cycles_and_are_late():
    link = FriLink(faults=LinkFaults(seed=0, reorder_probability=1.0))
    link.start(0)
    m0 = link.measurement(0, Q, POSE, FT)
    assert not link.deliver(answer(m0), 50_000)  # held back 1.5 ms: past its own deadline
    out0 = link.end_cycle(CYCLE)
    assert not out0.answered and link.statistics().late == 1
    assert link.faults.reordered == 1
    assert "deadline" in link.last_reject_reason


def test_faults_act_only_while_active():
    faults = LinkFaults(seed=2, drop_probability=1.0)
    link = FriLink(faults=faults)
    link.start(0)
    answered = []
    for k in range(300):
        faults.active = 100 <= k < 160  # a 60 ms dropout
        m = link.measurement(k * CYCLE, Q, POSE, FT)
        link.deliver(answer(m), k * CYCLE + 50_000)
        answered.append(link.end_cycle((k + 1) * CYCLE).answered)
    assert faults.dropped == 60 and answered[100:160] == [False] * 60
    assert all(answered[:100]) and all(answered[160:])


def test_adding_the_order_faults_keeps_the_other_faults_streams():
    """Duplication and reordering draw from a stream of their own: a seed's losses and
    corruptions are the same with them as without."""
    kw = dict(drop_probability=0.1, corrupt_probability=0.05)
    plain, _ = _faulty_run(LinkFaults(seed=9, **kw), 1000)
    ordered, _ = _faulty_run(LinkFaults(seed=9, duplicate_probability=0.2, **kw), 1000)
    assert (plain.faults.dropped, plain.faults.corrupted) == (ordered.faults.dropped, ordered.faults.corrupted)


@pytest.mark.parametrize("field, value", [("drop_probability", 1.5), ("seed", None), ("delay_ns", -1), ("jitter_ns", 0.5),
                                          ("duplicate_probability", -0.1), ("reorder_lag_ns", 1.5)])
def test_bad_fault_settings_name_field(field, value):
    kw = {"seed": 0, field: value}
    with pytest.raises(ValueError, match=rf"LinkFaults\.{field}"):
        LinkFaults(**kw)


def test_a_command_is_judged_field_by_field_in_order_and_names_the_value_as_sent():
    """The first problem in the order of the fields wins, whether it is a value (checked by
    the compiled check) or a shape (checked before it): a rotation that is not one comes
    before a stiffness of the wrong shape, which comes before a damping out of range; and
    the value at fault is named as the sender wrote it."""
    link = FriLink()
    link.start(0)
    good = answer(link.measurement(0, Q, POSE, FT))
    both = replace(good, cart_pos=np.zeros(12), cart_stiffness=np.zeros(5), cart_damping=np.full(6, 2.0))
    assert command_problem(both) == "cart_pos rotation is not orthonormal"
    assert command_problem(replace(both, cart_pos=POSE)) == "cart_stiffness has shape (5,), expected (6,)"
    assert command_problem(replace(both, cart_pos=POSE, cart_stiffness=np.zeros(6))) == \
        "cart_damping[0] = 2.0 outside [0, 1]"
    ints = replace(good, cart_stiffness=np.array([100, 6000, 0, 0, 0, 0]))
    assert command_problem(ints) == "cart_stiffness[1] = 6000 outside [0, 5000.0]"
    listed = replace(good, cart_stiffness=[100, 6000, 0, 0, 0, 0])
    assert command_problem(listed) == "cart_stiffness[1] = 6000.0 outside [0, 5000.0]"
    assert command_problem(replace(good, add_tcp_ft=np.full(6, 1e308))) == \
        "add_tcp_ft has values too large to be meaningful"
    assert command_problem(good) is None


def test_commands_checked_on_several_threads_at_once_each_get_their_own_answer():
    """The compiled check's buffers are shared: threads checking at the same time (a KRC's
    UDP endpoint beside the cycle) must each be told about their own packet."""
    import threading

    link = FriLink()
    link.start(0)
    good = answer(link.measurement(0, Q, POSE, FT))
    packets = [(good, None), (replace(good, cart_damping=np.full(6, 2.0)), "cart_damping[0] = 2.0 outside [0, 1]"),
               (replace(good, cart_stiffness=np.full(6, np.nan)), "cart_stiffness[0] is not finite (nan)"),
               (replace(good, cart_pos=np.zeros(12)), "cart_pos rotation is not orthonormal")]
    wrong = []

    def check(packet, expected):
        for _ in range(2000):
            got = command_problem(packet)
            if got != expected:
                wrong.append((expected, got))
                return

    threads = [threading.Thread(target=check, args=p) for p in packets]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert wrong == []
