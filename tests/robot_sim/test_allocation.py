"""The 1 ms control step allocates nothing, in every KRC mode.

The control step is what the cell runs between two FRI packets:

    sim.joint_positions(q); sim.joint_velocities(qd)
    tau = krc.compute(q, qd, command, hold=...)
    sim.apply(tau, hand_wrench); sim.step()

``tracemalloc`` sees Python objects, numpy array data (numpy registers its
allocator with it) and numba's runtime (PyMem_RawMalloc); a new 7-vector costs
56 B of data plus a ~100 B header, a numpy scalar 24 B and more.  It does not
see C++'s operator new: bench/sim_step.py counts those with a malloc counter
(eigenpy copies each numpy vector passed to Pinocchio: 2 x 56 B per step).
"""

import tracemalloc

import numpy as np
import pinocchio as pin
import pytest

from robot_sim.kinematics import READY, ArmKinematics
from robot_sim.krc import (
    POSITION,
    ImpedanceCommand,
    KrcController,
    SafetyReason,
    pose_to_cart_pos,
)
from robot_sim.physics import Simulation
from robot_sim.teacher import DOWN
from robot_sim.worlds import Valley, free_space, valley

WARM_UP = 300  # covers numba's first calls and several Lambda refreshes
STEPS = 2000
HAND = np.array([0.0, 1.5, -0.5, 0.05, 0.0, 0.02])  # a light touch: the hand path of apply() runs too


def stepper(sim, krc, command=None, hold=True, hand=HAND, external_force=None):
    q, qd = np.empty(7), np.empty(7)

    def step():
        sim.joint_positions(q)
        sim.joint_velocities(qd)
        tau = krc.compute(q, qd, command, hold=hold, external_force=external_force)
        sim.apply(tau, hand)
        sim.step()

    return step


def measure(step, steps=STEPS):
    """(net growth of traced memory over ``steps`` steps, largest transient of one step), bytes.

    The bookkeeping allocates nothing while tracing: the readings go into
    arrays, and the loop's iterator and ints exist before tracing starts."""
    for _ in range(WARM_UP):
        step()
    current = np.zeros(steps + 1, dtype=np.int64)
    peak = np.zeros(steps, dtype=np.int64)
    indices = iter(list(range(steps)))
    tracemalloc.start()
    try:
        for i in indices:
            current[i] = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            step()
            peak[i] = tracemalloc.get_traced_memory()[1]
        current[steps] = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    return int(current[steps] - current[0]), int((peak - current[:steps]).max())


def arm(world=None):
    kin = ArmKinematics()
    sim = Simulation(world or free_space())
    sim.reset(READY)
    return sim, kin, KrcController(kin)


def cart_imp():
    sim, kin, krc = arm()
    x0 = kin.forward(READY)
    target = pin.SE3(pin.exp3(np.array([0.0, 0.1, 0.2])) @ x0.rotation, x0.translation + [0.05, -0.04, 0.03])
    cmd = ImpedanceCommand(pose_to_cart_pos(target), np.array([2000.0] * 3 + [150.0] * 3), np.full(6, 0.7),
                           np.array([1.0, 0.0, -2.0, 0.0, 0.1, 0.0]))
    # the cell passes the force estimate every cycle
    return stepper(sim, krc, cmd, hold=False, external_force=np.array([0.0, 0.5, 1.0])), krc


def cart_imp_on_plate():
    g = Valley()
    sim, kin, krc = arm(valley(g))
    n = g.plate_normal(-1)
    y = -0.08
    contact = np.array([0.6, y, g.surface_z(y)]) + n * kin.description.tool.tip_radius
    sim.reset(kin.inverse_kinematics(pin.SE3(DOWN, contact + 0.002 * n), READY))
    cmd = ImpedanceCommand(pose_to_cart_pos(pin.SE3(DOWN, contact - 0.01 * n)), np.array([1000.0] * 3 + [150.0] * 3),
                           np.full(6, 0.7), np.zeros(6))
    return stepper(sim, krc, cmd, hold=False, hand=None), krc


def cartesian_hold():
    sim, _, krc = arm()
    return stepper(sim, krc, None, hold=True), krc


def gravity_compensation():
    sim, _, krc = arm()
    krc.gravity_compensation = True
    return stepper(sim, krc), krc


def position():
    sim, _, krc = arm()
    krc.switch_mode(POSITION)
    krc.set_joint_target(READY + np.array([0.2, -0.1, 0.1, 0.15, -0.2, 0.1, 0.3]))
    return stepper(sim, krc), krc


def joint_hold():
    sim, _, krc = arm()
    q = sim.joint_positions()
    krc.compute(q, np.zeros(7), external_force=np.array([0.0, 0.0, 1e3]))  # over the force limit: stop
    assert krc.safety == SafetyReason.CARTESIAN_FORCE
    return stepper(sim, krc), krc


MODES = {f.__name__: f for f in (cart_imp, cart_imp_on_plate, cartesian_hold, gravity_compensation, position,
                                 joint_hold)}


@pytest.mark.parametrize("mode", MODES)
def test_the_control_step_allocates_nothing(mode):
    step, krc = MODES[mode]()
    # tracemalloc sees every thread: a clean run out of three rules out another
    # thread's allocations (what the step allocates, it allocates every run)
    for _ in range(3):
        growth, worst = measure(step)
        if growth == 0 and worst == 0:
            break
    assert krc.safety == (SafetyReason.CARTESIAN_FORCE if mode == "joint_hold" else SafetyReason.NONE)
    assert growth == 0, f"{mode}: traced memory grew by {growth} B over {STEPS} steps"
    # not one byte: no array, view, numpy scalar or Python object in any step
    assert worst == 0, f"{mode}: a step allocated {worst} B (transient)"


def test_the_measurement_sees_what_a_step_allocates():
    step, _ = cartesian_hold()
    # a 7-vector (56 B of data and its header), a numpy scalar (24 B and more)
    for extra, at_least in ((lambda: np.empty(7), 56 + 96), (lambda: np.float64(1.0) + 1.0, 24)):
        def allocating(extra=extra):
            step()
            extra()

        _, worst = measure(allocating, 100)
        assert worst >= at_least
