"""The simulated teacher's demonstrations in the task worlds, run by the nodes (the robot,
the sensor, the teacher and the recorder in one process, the episode protocol of every
run), read back from the recording; and the same seed records the same trajectory."""

import math

import numpy as np
import pytest

from robot_sim.arm.description import LWR4
from robot_sim.world.tasks import HoseCoupler, Valley
from services.run.demonstration import demonstration_scenario, record_demonstration
from tests.support import recorded_samples

# whole runs in one process (seconds each): the slow lane
pytestmark = [pytest.mark.slow]

VALLEY_START = (0.68, -0.10, 0.40)  # the left side's; the right side mirrors y
SIDES = {-1: "left", 1: "right"}  # the sign of y on each side


def valley_demo(out, side, seed=0):
    """(report, recording) of a valley demonstration from ``side`` (-1 left, +1 right)."""
    report, path = record_demonstration(demonstration_scenario(
        "valley", side=SIDES[side], seed=seed, start=VALLEY_START, goal_x=0.45, max_seconds=30.0), out,
        progress=lambda line: None)
    assert report["error"] is None, report["error"]
    return report, path


@pytest.fixture(scope="module")
def left_demo(tmp_path_factory):
    """The left side's demonstration of seed 0: judged on its own and against its seed's second run."""
    return valley_demo(tmp_path_factory.mktemp("left") / "run", -1)


@pytest.mark.parametrize("side", [-1, 1])
def test_valley_demonstration_from_each_side(tmp_path, side, left_demo):
    report, path = left_demo if side == -1 else valley_demo(tmp_path / "run", side)
    d = recorded_samples(path)
    g = Valley()
    (demo,) = report["demonstrations"]
    assert demo["reason"] == "teacher_done"
    assert np.all(d["safety"] == 0)
    # the three phases, in order, each long enough to learn from
    assert list(np.unique(d["true_phase"])) == [0, 1, 2]
    assert np.all(np.diff(d["true_phase"]) >= 0)
    counts = np.bincount(d["true_phase"])
    assert counts.min() > 100  # samples at 100 Hz: over a second each
    p = d["position"]
    free, plate, groove = (d["true_phase"] == k for k in range(3))
    # free motion: moving down, no contact
    assert p[free][-1, 2] < p[free][0, 2] - 0.05
    assert np.abs(d["contact_force"][free]).max() < 1e-9
    # sliding along the plate on the starting side: y goes to the groove, z down
    assert np.all(np.sign(p[plate][:-5, 1]) == side)
    assert abs(p[plate][-1, 1]) < abs(p[plate][0, 1]) - 0.05
    # sliding along the groove: y ~ 0, x decreasing to the goal
    assert np.abs(p[groove][:, 1]).max() < 0.01
    assert p[groove][-1, 0] <= 0.45 + 1e-3
    tip = LWR4.tool.tip_radius
    assert np.abs(p[groove][:, 2] - (g.groove_z + tip / math.cos(g.angle))).max() < 3e-3
    # contact forces as in thesis fig. 13: zero in free motion, a few to tens of N in contact
    wrench_base = d["wrench_base"]
    f_plate = np.linalg.norm(wrench_base[plate][:, :3], axis=1)
    f_groove = np.linalg.norm(wrench_base[groove][:, :3], axis=1)
    assert np.linalg.norm(wrench_base[free][:, :3], axis=1).mean() < 1.0
    assert 3.0 < np.median(f_plate) < 40.0
    assert 3.0 < np.median(f_groove) < 40.0
    # on the plate the (tared) sensor sees the plate's push: towards the valley's middle and up
    mean_plate = wrench_base[plate][:, :3].mean(axis=0)
    assert -side * mean_plate[1] > 1.0 and mean_plate[2] > 1.0
    # in the groove: pushed up, and friction against the motion (towards +x)
    mean_groove = wrench_base[groove][:, :3].mean(axis=0)
    assert mean_groove[2] > 2.0 and mean_groove[0] > 0.5
    # the sensor agrees with the physics' contact force (after tare, up to noise and inertia)
    err = wrench_base[plate | groove][:, :3] - d["contact_force"][plate | groove]
    assert np.median(np.linalg.norm(err, axis=1)) < 1.5


def test_hose_coupler_demonstration_completes_its_rotation(tmp_path):
    start = HoseCoupler.start_left
    assert start == (0.62, -0.08, 0.36)
    report, path = record_demonstration(demonstration_scenario("hose_coupler", seed=3, max_seconds=30.0),
                                        tmp_path / "run", progress=lambda line: None)
    assert report["error"] is None, report["error"]
    (demo,) = report["demonstrations"]
    assert demo["reason"] == "teacher_done"
    assert demo["start"] == list(start)  # the world's default, no spread
    d = recorded_samples(path)
    assert np.all(d["safety"] == 0)
    assert list(np.unique(d["true_phase"])) == [0, 1]
    coupling = d["true_phase"] == 1
    assert coupling.sum() > 100
    # the tool turned a quarter turn about the vertical while coupling
    R = d["R"]
    R0, R1 = R[coupling][0], R[coupling][-1]
    turn = np.arctan2((R0.T @ R1)[1, 0], (R0.T @ R1)[0, 0])
    assert abs(abs(turn) - math.pi / 2) < math.radians(6)
    # inside the coupler, pressed into it, and the turn costs torque about the tool axis
    c = np.array(HoseCoupler().center)
    assert np.linalg.norm(d["position"][coupling][:, :2] - c[:2], axis=1).max() < 0.01
    assert d["wrench_base"][coupling][:, 2].mean() > 2.0
    turning = coupling & (np.abs(np.gradient(np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0])))) > 1e-3)
    assert np.abs(d["wrench"][turning][:, 5]).mean() > 0.1  # N m


def test_same_seed_same_trajectory(tmp_path, left_demo):
    """Every recorded cycle, not only the 100 Hz samples: the measured pose and the sensor's wrench."""
    a = recorded_samples(left_demo[1], period_ns=None)
    b, c = (recorded_samples(valley_demo(tmp_path / name, -1, seed=seed)[1], period_ns=None)
            for name, seed in (("b", 0), ("c", 6)))
    assert len(a["seq"]) > 10_000  # the whole demonstration, every FRI cycle
    np.testing.assert_array_equal(a["seq"], b["seq"])
    np.testing.assert_array_equal(a["pose"], b["pose"])
    np.testing.assert_array_equal(a["wrench"], b["wrench"])
    assert c["pose"].shape != a["pose"].shape or not np.array_equal(c["pose"], a["pose"])
