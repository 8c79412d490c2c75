"""The commander's per-phase law on its own (no network): the reference runs at the
phase's speed, a blocked tool is pushed with at most K times the lead, and the goal stops it."""

import numpy as np

from etar.impedance import derive_impedance
from services.impedance_commander import ImpedanceLaw

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
