"""The hose coupler reproduced in one process: teacher demonstrations, ETAR with a
pose state, per-phase impedance with the turn, then the commander's law closing
the loop through the KRC with the online phase filter - everything the services
do over Zenoh for this task, without the network."""

import math

import numpy as np
import pinocchio as pin
import pytest

from etar import ETAR
from etar.impedance import phase_impedances
from robot_sim.cell import RobotCell, standard_to_fri
from robot_sim.demonstration import record_demonstration, settle_and_tare
from robot_sim.fri import CommandPacket
from robot_sim.teacher import DOWN, HoseCouplerTeacher
from robot_sim.worlds import hose_coupler
from etar.features import force_vector, pose_of, state_vector
from etar.policy import ReproductionPolicy as ImpedanceLaw
from services.nodes.impedance_commander import CART_DAMPING as _CART_DAMPING, CART_STIFFNESS as _CART_STIFFNESS

START = np.array([0.62, -0.08, 0.36])


def demonstration(seed):
    cell = RobotCell(hose_coupler(), seed=seed)
    rng = np.random.default_rng(seed)
    start = START + rng.uniform(-0.01, 0.01, 3)
    cell.place_tcp(start, DOWN)
    cell.start()
    settle_and_tare(cell)
    teacher = HoseCouplerTeacher(cell.world.task, start, rng=rng)
    d = record_demonstration(cell, teacher, max_seconds=30.0,
                             done=lambda c, t: t.phase == 1 and t.rotation_done(c.sim.tcp_rotation()))
    assert d.completed
    R0 = d.rotations[0]
    states = np.array([state_vector(p, "pose", R0) for p in d.tcp_pose])
    forces = np.array([force_vector(w, p, "force_torque") for w, p in zip(d.wrench_sensor, d.tcp_pose)])
    return states, forces, d.dt


@pytest.fixture(scope="module")
def learned():
    demos = [demonstration(seed) for seed in (11, 12, 13)]
    pairs = [(s, f) for s, f, _ in demos]
    model = ETAR(2, "effect", n_restarts=2).fit(pairs, max_iter=100, seed=0)
    imps = phase_impedances(model, pairs, demos[0][2], rotation_columns=slice(3, 6))
    goal = np.mean([s[-1][:3] for s, _ in pairs], axis=0)
    goal_rotation = np.mean([s[-1][3:6] for s, _ in pairs], axis=0)
    return model, [None if i is None else i.to_dict() for i in imps], goal, goal_rotation


def test_the_coupling_phase_is_learned_as_done_in_place_and_turning(learned):
    _, imps, _, goal_rotation = learned
    approach, coupling = sorted(imps, key=lambda i: i["in_place"])
    assert not approach["in_place"] and approach["mean_speed"] > 0.02
    assert coupling["in_place"] and coupling["n_compliant"] == 1
    # pressed down into the coupler: the compliant axis is (nearly) vertical
    assert abs(coupling["compliant_axes"][0][2]) > 0.9
    # turning about the tool axis (the start frame's z: the tool points down)
    w = np.array(coupling["angular_velocity"])
    assert abs(w[2]) > 0.3 and np.linalg.norm(w[:2]) < 0.1 * abs(w[2])
    assert abs(abs(goal_rotation[2]) - math.pi / 2) < math.radians(15)


@pytest.mark.parametrize("offset", [(0.015, -0.012, 0.0), (-0.012, 0.015, 0.005)])
def test_a_reproduction_enters_the_coupler_and_turns_it(learned, offset):
    model, imps, goal, goal_rotation = learned
    cell = RobotCell(hose_coupler(), seed=40)
    start = START + np.array(offset)
    cell.place_tcp(start, DOWN)
    cell.start()
    settle_and_tare(cell)
    cell.krc.gravity_compensation = False
    cell.fri.request_command_mode()
    law = ImpedanceLaw(imps, goal, goal_rotation=goal_rotation)
    phase_filter = model.filter()
    phase, R0, peak = None, None, 0.0
    for _ in range(20_000):  # 20 s
        m = cell.begin_cycle()
        R, x = pose_of(m.msr_cart_pos)
        R0 = R.copy() if R0 is None else R0
        F, R_set = law.step(x, R, phase)
        cell.receive(CommandPacket(seq=m.seq, cart_pos=np.hstack([R_set, x[:, None]]).ravel(),
                                   cart_stiffness=np.array(_CART_STIFFNESS), cart_damping=np.array(_CART_DAMPING),
                                   add_tcp_ft=standard_to_fri(np.concatenate([R.T @ F, np.zeros(3)]))),
                     m.stamp_ns + 100_000)
        out = cell.end_cycle()
        peak = max(peak, float(np.linalg.norm(out.contact_force)))
        if m.stamp_ns % 10_000_000 == 0:  # the estimator's 100 Hz
            p = phase_filter.update(state_vector(m.msr_cart_pos, "pose", R0),
                                    force_vector(out.ft.wrench(cell.ati_config), m.msr_cart_pos, "force_torque"))
            phase = int(np.argmax(p))
        if law.goal_reached or cell.krc.safety:
            break
    assert cell.krc.safety == 0
    assert law.goal_reached
    c = np.array(cell.world.task.center)
    assert np.linalg.norm(x[:2] - c[:2]) < 0.01 and x[2] < c[2] + 0.02  # in the coupler, at its floor
    turned = pin.log3(R0.T @ R)
    assert abs(abs(turned[2]) - math.pi / 2) < math.radians(15), turned  # the quarter turn
    assert peak < 60.0  # the scenario's force bound
