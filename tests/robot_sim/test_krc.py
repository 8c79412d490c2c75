"""The KRC's control laws on the MuJoCo arm: gravity compensation, impedance, safety."""

import numpy as np
import pinocchio as pin
import pytest

from robot_sim.arm.kinematics import ArmKinematics, READY
from robot_sim.krc.law import ImpedanceCommand, KrcController, POSITION, SafetyReason, pose_to_cart_pos
from robot_sim.world.physics import Simulation
from robot_sim.world.teacher import DOWN
from robot_sim.world.tasks import Valley, free_space, valley


def run(sim, krc, cycles, command=None, hold=False, hand=None, external_force=None):
    q, qd = np.empty(7), np.empty(7)
    for _ in range(cycles):
        sim.joint_positions(q)
        sim.joint_velocities(qd)
        tau = krc.compute(q, qd, command, hold=hold if command is not None else True,
                          external_force=external_force)
        sim.apply(tau, hand)
        sim.step()
    return sim.joint_positions()


@pytest.fixture
def arm():
    kin = ArmKinematics()
    sim = Simulation(free_space())
    sim.reset(READY)
    return sim, kin, KrcController(kin)


def test_gravity_compensation_holds_the_arm_still(arm):
    sim, kin, krc = arm
    krc.gravity_compensation = True
    q_end = run(sim, krc, 2000)
    assert np.abs(q_end - READY).max() < 1e-6  # rad over 2 s
    assert np.linalg.norm(sim.tcp_position() - kin.forward(READY).translation) < 1e-6


def test_gravity_compensation_lets_a_small_hand_force_move_the_arm(arm):
    sim, kin, krc = arm
    krc.gravity_compensation = True
    x0 = sim.tcp_position()
    run(sim, krc, 1000, hand=np.array([0.0, 3.0, 0.0, 0.0, 0.0, 0.0]))  # 3 N sideways for 1 s
    moved = sim.tcp_position() - x0
    assert moved[1] > 0.01  # centimetres, in the pushed direction
    # without the hand force a stiff impedance would not have budged
    sim.reset(READY)
    krc.gravity_compensation = False
    cmd = ImpedanceCommand(pose_to_cart_pos(kin.forward(READY)), np.array([3000.0] * 3 + [200.0] * 3),
                           np.full(6, 0.7), np.zeros(6))
    x0 = sim.tcp_position()
    run(sim, krc, 1000, command=cmd, hand=np.array([0.0, 3.0, 0.0, 0.0, 0.0, 0.0]))
    assert abs((sim.tcp_position() - x0)[1] - 3.0 / 3000.0) < 5e-4


def test_impedance_tracks_a_setpoint_in_free_space(arm):
    sim, kin, krc = arm
    x0 = kin.forward(READY)
    target = pin.SE3(pin.exp3(np.array([0.0, 0.0, 0.2])) @ x0.rotation, x0.translation + [0.05, -0.04, 0.03])
    cmd = ImpedanceCommand(pose_to_cart_pos(target), np.array([2000.0] * 3 + [150.0] * 3), np.full(6, 0.7),
                           np.zeros(6))
    run(sim, krc, 2500, command=cmd)
    np.testing.assert_allclose(sim.tcp_position(), target.translation, atol=5e-4)
    err = pin.log3(sim.tcp_rotation().T @ target.rotation)
    assert np.linalg.norm(err) < 5e-3
    assert krc.safety == SafetyReason.NONE


def test_impedance_presses_with_the_expected_force_against_a_plate():
    g = Valley()
    kin = ArmKinematics()
    sim = Simulation(valley(g))
    krc = KrcController(kin)
    n = g.plate_normal(-1)
    y = -0.08
    surface = np.array([0.6, y, g.surface_z(y)])
    tip = kin.description.tool.tip_radius
    touching_pose = surface + n * tip
    sim.reset(kin.inverse_kinematics(pin.SE3(DOWN, touching_pose + 0.005 * n), READY))
    k, depth = 1000.0, 0.01
    cmd = ImpedanceCommand(pose_to_cart_pos(pin.SE3(DOWN, touching_pose - depth * n)),
                           np.array([k] * 3 + [150.0] * 3), np.full(6, 1.0), np.zeros(6))
    run(sim, krc, 3000, command=cmd)
    f, roles = sim.contact_wrench()
    assert roles == {"plate"}
    assert f @ n == pytest.approx(k * depth, rel=0.1)  # spring force k * depth along the normal
    assert np.linalg.norm(f - (f @ n) * n) < 0.3 * k * depth  # friction stays inside its cone


def test_position_mode_moves_to_a_joint_target(arm):
    sim, kin, krc = arm
    krc.switch_mode(POSITION)
    target = READY + np.array([0.2, -0.1, 0.1, 0.15, -0.2, 0.1, 0.3])
    krc.set_joint_target(target)
    q = run(sim, krc, 3000)
    np.testing.assert_allclose(q, target, atol=2e-3)
    assert krc.reached_target


def test_joint_limit_stops_the_arm_safely(arm):
    sim, kin, krc = arm
    krc.gravity_compensation = True
    q0 = READY.copy()
    q0[0] = np.deg2rad(160.0)
    sim.reset(q0)
    kin.update(q0)
    push = kin.jacobian("flange")[:3, 0]  # the flange's motion per unit of joint 1
    # a hand swinging joint 1 hard towards its +170 deg limit
    q = run(sim, krc, 3000, hand=np.concatenate([30.0 * push / np.linalg.norm(push), np.zeros(3)]))
    assert krc.safety == SafetyReason.JOINT_LIMIT
    assert np.all(np.isfinite(q))
    assert np.all(q > np.array(kin.description.q_min) - 0.02) and np.all(q < np.array(kin.description.q_max) + 0.02)
    # once stopped the arm is held, not thrown around
    q1 = run(sim, krc, 500, hand=np.zeros(6))
    assert np.abs(sim.joint_velocities()).max() < 0.05
    assert np.abs(q1 - run(sim, krc, 200)).max() < 1e-3


def test_cartesian_force_limit_and_non_finite_state_stop_the_arm(arm):
    sim, kin, krc = arm
    run(sim, krc, 10, external_force=np.array([0.0, 0.0, 200.0]))
    assert krc.safety == SafetyReason.CARTESIAN_FORCE
    krc.reset_safety()
    assert krc.safety == SafetyReason.NONE
    tau = krc.compute(np.full(7, np.nan), np.zeros(7))
    assert krc.safety == SafetyReason.NON_FINITE
    assert np.all(np.isfinite(tau))


def test_saturated_torques_stop_the_arm(arm):
    sim, kin, krc = arm
    x0 = kin.forward(READY)
    far = pin.SE3(x0.rotation, x0.translation + np.array([3.0, 0.0, 0.0]))  # unreachable, stiff
    cmd = ImpedanceCommand(pose_to_cart_pos(far), np.array([5000.0] * 3 + [300.0] * 3), np.full(6, 0.7),
                           np.zeros(6))
    q = run(sim, krc, 3000, command=cmd)
    assert krc.safety in (SafetyReason.TORQUE_SATURATION, SafetyReason.JOINT_LIMIT)
    assert np.all(np.isfinite(q))
    assert np.abs(sim.joint_velocities()).max() < 0.5


def test_a_command_loaded_from_the_fri_links_slot_is_load_numbers_of_its_rows():
    """``load_applied`` reads the link's slot (rows cart_pos, cart_stiffness, cart_damping,
    add_tcp_ft; the wrench in FRI's order Tz Ty Tx) as ``load_numbers`` of the rows, the
    wrench turned to the law's order: every buffer the same, bit for bit."""
    from kernel_plumbing.addresses import address
    from robot_sim.krc.packets import fri_order

    kin = ArmKinematics()
    a, b = KrcController(kin), KrcController(ArmKinematics())
    slot = np.random.default_rng(5).standard_normal((8, 12))
    a.load_applied(address(slot))
    b.load_numbers(slot[0], slot[1, :6], slot[2, :6], fri_order(slot[3, :6]))
    for name in ("_pose_cmd", "_stiffness", "_damping", "_wrench"):
        assert getattr(a, name).tolist() == getattr(b, name).tolist(), name
    assert a._wrench.tolist() != slot[3, :6].tolist()  # the torques did turn
