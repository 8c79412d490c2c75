"""The reproduction policy compiled (etar.policy_kernel) gives the Python policy's numbers
bit for bit, through every branch of its step: the hold before any phase, a new phase, a
phase handed to its successor when blocked, the slide along a surface met in free
space, the aim for a
place, the way to the place and the law there, the goal."""

import numpy as np
import pytest

from kernel_plumbing import blas
from etar.impedance import derive_impedance
from etar.policy import ReproductionPolicy
from etar.task import load_task
from tests.support import SMOKE_MODEL

pytestmark = pytest.mark.skipif(not blas.AVAILABLE, reason=f"numpy's OpenBLAS not reachable: {blas.WHY}")

DOWN = np.diag([-1.0, 1.0, -1.0])


def free_motion(direction, speed=0.04, seed=0):
    rng = np.random.default_rng(seed)
    d = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    v = speed * d + 0.001 * rng.normal(size=(200, 3))
    return derive_impedance(v, 0.2 * rng.normal(size=(200, 3)))


def pressing(place, seed=1):
    """A phase done in place, pressing down (soft z), not turning."""
    rng = np.random.default_rng(seed)
    n = 300
    v = 0.002 * rng.normal(size=(n, 3))
    f = np.array([0.0, 0.0, 8.5]) + 0.3 * rng.normal(size=(n, 3))
    x = np.asarray(place) + 0.001 * rng.normal(size=(n, 3))
    return derive_impedance(v, f, positions=x)


def policies():
    """(name, impedances, goal, where the tool starts, the first phase estimated) of
    policies that reach every branch between them."""
    smoke = load_task(SMOKE_MODEL)
    approach = free_motion((-0.3, 0.0, -1.0)).to_dict()
    approach["successor"] = 1  # free motion into a phase done in place: it aims for that place
    press = pressing((0.55, 0.0, 0.21)).to_dict()
    slide = free_motion((-1.0, 0.0, 0.0), seed=3).to_dict()
    slide["successor"] = 1  # blocked at the wall, the law goes on with the way down
    return [("smoke model", list(smoke.impedances), np.asarray(smoke.goal), (0.62, 0.0, 0.215), 2),
            # the goal away from the place: reaching it there would end the phase before it arrives
            ("approach, press in place", [approach, press], np.array([0.40, 0.0, 0.21]), (0.62, 0.0, 0.30), 0),
            ("slide, handed to its successor", [slide, free_motion((0.0, 0.0, -1.0), seed=4).to_dict()],
             np.array([0.45, 0.0, 0.20]), (0.62, 0.0, 0.30), 0),
            # down and along: it meets the floor and slides along it to the wall; the goal
            # beyond the wall, so that it presses on when the estimate changes and returns
            ("press on the floor, then slide", [free_motion((-1.0, 0.0, -1.0), seed=5).to_dict()],
             np.array([0.30, 0.0, 0.20]), (0.62, 0.0, 0.30), 0)]


def drive(policy, rng, start, first, tool, steps=10_000):
    """The policy's answers to a tool that follows its reference (with a floor and a wall
    it cannot pass, and noise), a phase estimate that changes now and then (None and
    unknown phases too), a contact force, and cycles that are sometimes two long.  With
    ``tool``, through ``tool_step``: the pose as 12 numbers and the force in tool axes,
    the tool turned a little off DOWN."""
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(0.3), -np.sin(0.3)], [0.0, np.sin(0.3), np.cos(0.3)]])
    R = DOWN @ tilt if tool else DOWN
    x = np.array(start) + rng.normal(0, 0.002, 3)
    phase = None
    n = len(policy.phases)
    for k in range(steps):
        if k == 200:
            phase = first  # long enough to arrive (at a place, a wall, the goal)
        elif k > 5500 and rng.random() < 0.002:
            phase = [None, 0, 0, 0, 1, 1, 1, n - 1, n, -1][rng.integers(10)]
        # a floor at z = 0.20 and a wall at x = 0.45 push back
        force = np.array([12.0 * (x[0] < 0.4501), 0.0, 12.0 * (x[2] < 0.2001)]) + rng.normal(0, 0.5, 3)
        dt = 0.002 if rng.random() < 0.03 else 0.001
        if tool:
            pose = np.concatenate([R, x[:, None]], axis=1).ravel().tolist()
            F, R_set, at = policy.tool_step(pose, (R.T @ force).tolist(), phase, dt)
            assert at.tolist() == x.tolist()
        else:
            F, R_set = policy.step(x.copy(), R, phase, dt, force)
        yield k, F, R_set
        ref = policy.ref
        if ref is not None:  # a fifth of the way to the reference each cycle
            x = x + 0.2 * (ref - x)
        x = x + rng.normal(0, 2e-5, 3)
        x[0], x[2] = max(x[0], 0.45), max(x[2], 0.20)
        if rng.random() < 0.001:
            x = x + rng.normal(0, 0.01, 3)  # a jump: the aim's and the place's far branches


@pytest.mark.parametrize("tool", [False, True], ids=["step", "tool_step"])
@pytest.mark.parametrize("name,impedances,goal,start,first", policies(), ids=[p[0] for p in policies()])
def test_the_compiled_step_is_the_python_step_bit_for_bit(name, impedances, goal, start, first, tool):
    from etar.policy_kernel import CompiledPolicy, compilable

    seen = set()
    for seed in range(2):
        python = ReproductionPolicy(impedances, goal, goal_tolerance=0.01)
        assert compilable(python)
        compiled = CompiledPolicy(ReproductionPolicy(impedances, goal, goal_tolerance=0.01))
        for (k, F1, R1), (_, F2, R2) in zip(drive(python, np.random.default_rng(seed), start, first, tool),
                                            drive(compiled, np.random.default_rng(seed), start, first, tool)):
            assert F1.tobytes() == F2.tobytes(), (name, seed, k, F1, F2)
            assert R1.tobytes() == R2.tobytes()
            assert (python.applied, python.goal_reached, python.phase) == (
                compiled.applied, compiled.goal_reached, compiled.phase), (name, seed, k)
            assert python.v.tobytes() == compiled.v.tobytes()
            assert (python.ref is None) == (compiled.ref is None)
            assert python.ref is None or python.ref.tobytes() == compiled.ref.tobytes(), (name, seed, k)
            seen |= {"hold" if python.applied is None else "law", "goal" if python.goal_reached else "",
                     "handed" if python.handed is not None else "", "at place" if python.at_place else "",
                     "slid" if python.applied == 0 and python.last_d is not None
                     and np.linalg.norm(python.last_d - python.phases[0].direction) > 0.1 else "",
                     "aim" if any(law is not None and law.aim is not None and python.applied == p
                                  for p, law in enumerate(python.phases)) else ""}
    # the branches this policy has were taken
    assert {"hold", "law"} <= seen, seen
    if name.startswith("approach"):
        assert {"aim", "at place"} <= seen, seen
    elif not name.startswith("press"):
        assert "goal" in seen, seen
    if name.startswith("slide"):
        assert "handed" in seen, seen
    if name.startswith("press"):
        assert "slid" in seen, seen


def test_a_turning_policy_stays_in_python():
    from etar.policy_kernel import compilable, compiled_policy

    rng = np.random.default_rng(1)
    turning = derive_impedance(0.002 * rng.normal(size=(300, 3)), np.array([0.0, 0.0, 8.5]) + rng.normal(size=(300, 3)),
                               angular_velocities=np.array([0.0, 0.0, -0.6]) + 0.01 * rng.normal(size=(300, 3)),
                               positions=0.001 * rng.normal(size=(300, 3)))
    policy = ReproductionPolicy([turning.to_dict()], goal=None)
    assert not compilable(policy) and compiled_policy(policy) is policy
