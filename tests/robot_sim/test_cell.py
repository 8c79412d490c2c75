"""The cell's FRI cycle: quality drops and CMD falls back to MON on late or missing
answers, the arm holds meanwhile, and everything recovers."""

import numpy as np

import pytest

from robot_sim.cell import JOINT_POSITION_NOISE, RobotCell
from robot_sim.krc.packets import CommandPacket, ControlMode, FriQuality, FriState, fri_order
from robot_sim.world.tasks import free_space

STIFF = np.array([2000.0] * 3 + [150.0] * 3)


def cycle(cell, delay_ns=None):
    m = cell.begin_cycle()
    if delay_ns is not None:
        cmd = CommandPacket.from_measurement(m, cart_stiffness=STIFF, cart_damping=np.full(6, 0.7))
        cell.receive(cmd, m.stamp_ns + delay_ns)
    return cell.end_cycle()


def test_quality_and_command_mode_follow_the_answers():
    cell = RobotCell(free_space(), seed=0)
    cell.start()
    x0 = cell.sim.tcp_position()
    for _ in range(600):
        out = cycle(cell, 200_000)  # answered after 0.2 ms
    assert out.outcome.quality == FriQuality.PERFECT and out.outcome.state == FriState.MON
    assert cell.fri.request_command_mode()
    out = cycle(cell, 200_000)
    assert out.outcome.state == FriState.CMD and not out.outcome.hold
    for _ in range(200):
        out = cycle(cell, 200_000)
    assert out.outcome.command is not None
    # a single missing answer is bridged by repeating the last command
    out = cycle(cell, None)
    assert out.outcome.bridged and out.outcome.state == FriState.CMD
    # answers arriving after the deadline: misses, quality falls, back to MON and hold
    states, qualities = [], []
    for _ in range(30):
        out = cycle(cell, 1_500_000)
        states.append(out.outcome.state)
        qualities.append(out.outcome.quality)
    assert states[-1] == FriState.MON and out.outcome.hold
    assert min(qualities) <= FriQuality.BAD
    assert cell.fri.statistics().late >= 30
    # the arm held its pose all along (Cartesian hold in MON)
    assert np.linalg.norm(cell.sim.tcp_position() - x0) < 2e-3
    assert cell.krc.safety == 0
    # answers in time again: quality recovers; CMD needs a new request
    for _ in range(700):
        out = cycle(cell, 200_000)
    assert out.outcome.quality == FriQuality.PERFECT and out.outcome.state == FriState.MON
    cell.fri.request_command_mode()
    out = cycle(cell, 200_000)
    assert out.outcome.state == FriState.CMD


def test_control_mode_switch_only_in_monitor_mode():
    cell = RobotCell(free_space(), seed=0)
    cell.start()
    for _ in range(600):
        cycle(cell, 100_000)
    cell.fri.request_command_mode()
    cycle(cell, 100_000)
    assert cell.fri.state == FriState.CMD
    assert not cell.switch_control_mode(ControlMode.POSITION)
    assert cell.krc.mode == ControlMode.CART_IMP
    cell.fri.request_monitor_mode()
    assert cell.switch_control_mode(ControlMode.POSITION)
    assert cell.krc.mode == ControlMode.POSITION


def test_measurement_carries_the_state_and_the_external_force():
    cell = RobotCell(free_space(), seed=0)
    cell.start()
    cell.krc.gravity_compensation = True
    push = np.array([0.0, 0.0, -10.0, 0.0, 0.0, 0.0])  # 10 N down at the flange
    for _ in range(3):
        m = cell.begin_cycle()
        cell.end_cycle(push)
    m = cell.begin_cycle()
    R = m.msr_cart_pos.reshape(3, 4)[:, :3]
    est = fri_order(m.est_ext_tcp_ft)
    np.testing.assert_allclose(R @ est[:3], push[:3], atol=0.2)  # force in tcp axes -> world
    np.testing.assert_allclose(m.msr_jnt_pos, cell.sim.joint_positions(), rtol=0, atol=6 * cell.joint_noise)
    np.testing.assert_array_equal(fri_order(fri_order(np.arange(6.0))), np.arange(6.0))


def test_measured_joint_positions_carry_the_configured_white_noise():
    cell = RobotCell(free_space(), seed=3)
    cell.start()
    cell.krc.gravity_compensation = True
    errors, cart = [], []
    for _ in range(3000):
        m = cell.begin_cycle()
        errors.append(m.msr_jnt_pos - cell.sim.joint_positions())
        cart.append(m.msr_cart_pos.reshape(3, 4)[:, 3] - cell.kin.forward(cell.sim.joint_positions()).translation)
        cell.end_cycle()
    e = np.array(errors)
    assert cell.joint_noise == JOINT_POSITION_NOISE
    np.testing.assert_allclose(e.std(axis=0), JOINT_POSITION_NOISE, rtol=0.1)
    assert np.abs(e.mean(axis=0)).max() < 0.1 * JOINT_POSITION_NOISE
    # white: consecutive errors uncorrelated
    lag1 = [np.corrcoef(e[1:, j], e[:-1, j])[0, 1] for j in range(7)]
    assert max(abs(c) for c in lag1) < 0.1
    # the reported tcp pose is the forward kinematics of the measured joints: tens of um
    c = np.array(cart)
    assert 3e-6 < c.std(axis=0).min() and c.std(axis=0).max() < 6e-5


def test_noise_free_measurement_and_bad_noise():
    cell = RobotCell(free_space(), seed=0, joint_noise=0.0)
    cell.start()
    m = cell.begin_cycle()
    np.testing.assert_array_equal(m.msr_jnt_pos, cell.sim.joint_positions())
    for bad in (-1e-5, float("nan")):
        with pytest.raises(ValueError, match="joint_noise"):
            RobotCell(free_space(), joint_noise=bad)


def test_a_safety_stop_does_not_carry_into_the_next_placement():
    # a hand pushing 300 N latches the Cartesian force limit; placed elsewhere for the
    # next episode, the arm must start clean (the stale hand torque once re-latched it)
    from robot_sim.world.teacher import DOWN
    from robot_sim.world.tasks import valley

    cell = RobotCell(valley(), seed=0)
    cell.place_tcp(np.array([0.6, -0.08, 0.32]), DOWN)
    cell.start()
    cell.krc.gravity_compensation = True
    for _ in range(20):
        cell.begin_cycle()
        cell.end_cycle(np.array([0.0, 0.0, -300.0, 0.0, 0.0, 0.0]))
    assert cell.krc.safety == 2  # CARTESIAN_FORCE
    cell.place_tcp(np.array([0.66, -0.10, 0.40]), DOWN)
    cell.krc.gravity_compensation = False
    for _ in range(300):
        m = cell.begin_cycle()
        cell.end_cycle()
        assert cell.krc.safety == 0
    assert np.linalg.norm(fri_order(m.est_ext_tcp_ft)[:3]) < 5.0


def test_a_measurement_without_its_packet_is_the_packet_and_the_next_cycles_are_the_same():
    """``measure`` + ``measured_views`` + ``FriLink.sent_header`` say what ``begin_cycle``'s packet
    says, cycle by cycle, through MON, a command-mode request, CMD and missed answers; and an
    ``external_wrench_tcp`` read between measuring and closing, at other joint positions, does not
    change the estimate the KRC's law takes (the two cells stay bit for bit the same)."""
    a, b = RobotCell(free_space(), seed=3), RobotCell(free_space(), seed=3)
    for cell in (a, b):
        cell.start()
    states = set()
    for k in range(700):
        if k == 600:
            assert a.fri.request_command_mode() and b.fri.request_command_mode()
        m = a.begin_cycle()
        # the estimate in FRI's order (torques Tz Ty Tx), as the KRC's kinematics give it now
        assert m.est_ext_tcp_ft.tolist() == fri_order(a.external_wrench_tcp()).tolist()
        seq = b.measure()
        b.kin.update_with_jacobian(np.zeros(7), "tcp", np.empty((6, 7)))  # the estimate here is another
        b.external_wrench_tcp()
        q, x, ft = b.measured_views()
        reflected, state, quality, mode, *figures = b.fri.sent_header()
        assert (seq, reflected, state, quality, mode) == (m.seq, m.reflected_seq, m.state, m.quality, m.control_mode)
        assert figures == [m.answer_rate, m.latency_s, m.jitter_s, m.miss_rate]
        assert q.tolist() == m.msr_jnt_pos.tolist() and x.tolist() == m.msr_cart_pos.tolist()
        assert ft.tolist() == m.est_ext_tcp_ft.tolist()
        states.add(m.state)
        if k < 660 or k % 7:  # then every seventh cycle unanswered
            for cell in (a, b):
                cmd = CommandPacket.from_measurement(m, cart_stiffness=STIFF, cart_damping=np.full(6, 0.7))
                cell.receive(cmd, m.stamp_ns + 200_000)
        hand = np.array([3.0, -2.0, -8.0, 0.0, 0.0, 0.0])  # a hand on the tool: the estimate is not zero
        a.close(hand)
        b.close(hand)
        assert a.krc._force.tolist() == b.krc._force.tolist() == ft[:3].tolist()  # the estimate the law took
    assert states == {FriState.MON, FriState.CMD}
    assert a.sim.data.qpos.tolist() == b.sim.data.qpos.tolist()
    assert a.krc.torques.tolist() == b.krc.torques.tolist()
