"""The commander's per-phase law on its own (no network): the reference runs at the
phase's speed, a blocked tool is pushed with at most K times the lead, and the goal stops it."""

import numpy as np

from etar.impedance import derive_impedance
from etar.policy import ReproductionPolicy as ImpedanceLaw

DOWN = np.diag([-1.0, 1.0, -1.0])


def free_motion(direction=(0.0, 0.0, -1.0), speed=0.04):
    rng = np.random.default_rng(0)
    d = np.asarray(direction) / np.linalg.norm(direction)
    v = speed * d + 0.001 * rng.normal(size=(200, 3))
    return derive_impedance(v, 0.2 * rng.normal(size=(200, 3))).to_dict()


def test_blocked_tool_is_pushed_with_at_most_stiffness_times_lead():
    law = ImpedanceLaw([free_motion()], goal=None, lead=0.005)
    x = np.array([0.6, 0.0, 0.3])
    for _ in range(3000):  # 3 s against a floor: the reference would be 12 cm ahead unclamped
        F, R = law.step(x, DOWN, 0)
    assert -2000.0 * 0.005 - 1e-9 <= F[2] < -9.0  # 10 N down, no more
    np.testing.assert_allclose(F[:2], 0.0, atol=0.1)  # the derived direction is vertical within noise
    np.testing.assert_array_equal(R, DOWN)  # the start orientation is held


def test_reference_moves_at_the_phase_speed_and_the_goal_stops_it():
    law = ImpedanceLaw([free_motion(speed=0.04)], goal=np.array([0.6, 0.0, 0.28]), lead=0.005,
                       goal_tolerance=0.002)
    x = np.array([0.6, 0.0, 0.3])
    for k in range(400):  # a tool that follows the reference exactly
        law.step(x, DOWN, 0)
        x = law.ref.copy()
        if law.goal_reached:
            break
    # 2 cm less the 2 mm tolerance and half a lead of head start, at 4 cm/s: 0.39 s
    assert law.goal_reached and 0.37 < k * 1e-3 < 0.41, k
    for _ in range(100):  # the tool comes to rest
        F, _ = law.step(x, DOWN, 0)
    np.testing.assert_allclose(F, 0.0, atol=1e-6)  # at the goal the reference stops on the tool


def coupling(place=(0.55, 0.0, 0.21), turn_rate=-0.6):
    """A phase demonstrated in place: pressing down (soft z), turning about the tool axis."""
    rng = np.random.default_rng(1)
    n = 300
    v = 0.002 * rng.normal(size=(n, 3))
    f = np.array([0.0, 0.0, 8.5]) + 0.3 * rng.normal(size=(n, 3))
    w = np.array([0.0, 0.0, turn_rate]) + 0.01 * rng.normal(size=(n, 3))
    x = np.asarray(place) + 0.001 * rng.normal(size=(n, 3))
    return derive_impedance(v, f, angular_velocities=w, positions=x).to_dict()


def rotvec(R):
    import pinocchio as pin
    return pin.log3(R)


def test_a_turning_phase_turns_the_setpoint_at_its_rate_within_the_lead_and_stops_at_the_goal_turn():
    from etar.policy import ROT_LEAD

    imp = coupling(turn_rate=-0.6)
    assert abs(imp["angular_velocity"][2] + 0.6) < 0.01
    law = ImpedanceLaw([imp], goal=np.array([0.55, 0.0, 0.21]), goal_rotation=np.array([0.0, 0.0, -1.5]))
    x = np.array(imp["mean_position"])
    # a tool that does not turn: the setpoint runs ahead by the lead, no more
    for _ in range(1000):
        _, R_set = law.step(x, DOWN, 0)
    np.testing.assert_allclose(rotvec(DOWN.T @ R_set), [0.0, 0.0, -ROT_LEAD], atol=1e-3)
    assert np.linalg.norm(rotvec(DOWN.T @ R_set)) <= ROT_LEAD + 1e-12
    assert not law.goal_reached  # in place, but not turned
    # a tool that follows the setpoint: 0.6 rad/s, and not past the goal's turn
    R = DOWN
    for k in range(5000):
        _, R_set = law.step(x, R, 0)
        R = R_set
        if law.goal_reached:
            break
    turned = rotvec(DOWN.T @ R)
    assert law.goal_reached and abs(turned[2] + 1.5) < 0.1, turned
    # from -0.1 to within 0.1 rad of -1.5 at 0.6 rad/s: about 2.2 s
    assert 1.9 < k * 1e-3 < 2.5, k
    for _ in range(2000):  # held there
        _, R_set = law.step(x, R, 0)
    assert rotvec(DOWN.T @ R_set)[2] >= -1.5 - 1e-9


def test_a_phase_done_in_place_goes_there_stiffly_then_presses():
    from etar.policy import HOLD_STIFFNESS, PLACE_SPEED

    imp = coupling(place=(0.55, 0.0, 0.21), turn_rate=0.0)
    law = ImpedanceLaw([imp], goal=None)
    x = np.array([0.57, 0.0, 0.24])  # on the rim, 3.6 cm from the place
    F, _ = law.step(x, DOWN, 0)
    # on the way: the hold law, at most a lead from the tool, no push
    assert np.linalg.norm(F) <= HOLD_STIFFNESS * law.lead + 1e-9
    np.testing.assert_allclose(law.ref - x, (np.array(imp["mean_position"]) - x) / np.linalg.norm(
        np.array(imp["mean_position"]) - x) * PLACE_SPEED * 1e-3, atol=1e-12)
    for _ in range(5000):  # a tool that follows the reference
        law.step(x, DOWN, 0)
        x = law.ref.copy()
    assert law.at_place
    np.testing.assert_allclose(x, imp["mean_position"], atol=1e-9)
    F, _ = law.step(x, DOWN, 0)
    np.testing.assert_allclose(F, [0.0, 0.0, -8.5], atol=0.3)  # the demonstrated press, into the floor


def test_a_model_without_orientation_holds_the_start_orientation_exactly():
    law = ImpedanceLaw([free_motion()], goal=None, goal_rotation=None)
    R0 = np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    x = np.array([0.6, 0.0, 0.3])
    for _ in range(500):
        _, R_set = law.step(x, R0 @ np.diag([1.0, 1.0, 1.0]), 0)
    assert R_set is law.R_hold
    # a pose model whose demonstrations did not turn has no goal turn either
    assert ImpedanceLaw([free_motion()], goal=None, goal_rotation=[0.0, 0.02, -0.05]).goal_rotation is None


def test_free_phase_slides_along_a_surface_it_meets_pressing_as_it_goes():
    from etar.policy import HOLD_STIFFNESS

    # a 45-degree slope whose contact force points up and to +y; the free phase goes straight down
    law = ImpedanceLaw([free_motion()], goal=None, lead=0.005)
    x = np.array([0.6, 0.0, 0.3])
    n = np.array([0.0, 1.0, 1.0]) / np.sqrt(2.0)
    for _ in range(50):
        F, _ = law.step(x, DOWN, 0, force=8.0 * n)
    # the reference keeps the lead into the surface it had: a bounded push, the contact
    # the estimator's transition into the plate was learned on
    push = -(F @ n)
    assert 1.0 < push <= HOLD_STIFFNESS * law.lead + 1.0
    for _ in range(500):
        F2, _ = law.step(x, DOWN, 0, force=8.0 * n)
    assert abs(-(F2 @ n) - push) < 0.5  # it does not grow as the reference moves on
    along = F2 - (F2 @ n) * n
    assert along[1] > 3.0 and along[2] < -3.0  # down the slope
    F, _ = law.step(x, DOWN, 0)  # force unknown: the learned direction, as before
    assert F[2] < -5.0


def test_blocked_phase_hands_over_to_its_successor():
    rng = np.random.default_rng(2)
    down = free_motion()
    along = free_motion(direction=(-1.0, 0.0, 0.0))
    from dataclasses import replace
    from etar.impedance import PhaseImpedance
    down = replace(PhaseImpedance.from_dict(down), successor=1)
    law = ImpedanceLaw([down, along], goal=None, lead=0.005)
    x = np.array([0.6, 0.0, 0.3])
    floor = np.array([0.0, 0.0, 10.0])  # straight into the floor: no sliding, blocked
    for k in range(400):
        F, _ = law.step(x + 1e-5 * rng.normal(size=3), DOWN, 0, force=floor)
    assert F[2] < -5.0 and abs(F[0]) < 1.0  # still pressing down before STALL_TIME
    for k in range(200):
        F, _ = law.step(x + 1e-5 * rng.normal(size=3), DOWN, 0, force=floor)
    assert law.handed == 1 and F[0] < -5.0  # the successor's law: along -x
    law.step(x, DOWN, 1, force=floor)
    assert law.handed is None  # the estimator's phase rules again
