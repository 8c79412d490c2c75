"""Kinesthetic teaching in one process: a teacher guides the cell's arm in
gravity compensation while the arm state and the F/T sensor are sampled.

This is what the robot, ft_sensor, teacher and recorder services do together
over Zenoh, without the network: for tests, pictures and offline data sets.
Samples are taken every ``sample_every`` cycles (10: 100 Hz, as the thesis
recorded).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_sim.cell import RobotCell
from robot_sim.teacher import Teacher


@dataclass
class Demonstration:
    t: np.ndarray  # (T,) s
    q: np.ndarray  # (T, 7) measured joint positions
    tcp_pose: np.ndarray  # (T, 12) 3x4 row-major, base frame (FRI msrCartPos)
    wrench_sensor: np.ndarray  # (T, 6) tared ATI reading, sensor frame [F; T]
    wrench_base: np.ndarray  # (T, 6) the same in base axes (force the environment exerts on the tool)
    contact_force: np.ndarray  # (T, 3) true contact force on the tip, base axes (from the physics)
    true_phase: np.ndarray  # (T,) the teacher's physical label
    completed: bool
    dt: float

    @property
    def positions(self) -> np.ndarray:
        return self.tcp_pose.reshape(-1, 3, 4)[:, :, 3]

    @property
    def rotations(self) -> np.ndarray:
        return self.tcp_pose.reshape(-1, 3, 4)[:, :, :3]

    def step_phases(self) -> np.ndarray:
        """The label of every step t -> t+1 (ETAR's T-1 phases): the phase at t+1,
        since a step that ends in contact is governed by the contact."""
        return self.true_phase[1:]


def settle_and_tare(cell: RobotCell, cycles: int = 200, tare_samples: int = 100) -> None:
    """Hold still in gravity compensation and tare the sensor (tool weight out)."""
    cell.krc.gravity_compensation = True
    for k in range(cycles):
        if k == cycles - tare_samples:
            cell.ati.tare(tare_samples)
        cell.begin_cycle()
        cell.end_cycle()


def record_demonstration(cell: RobotCell, teacher: Teacher, *, sample_every: int = 10,
                         max_seconds: float = 60.0, done=None) -> Demonstration:
    """Run the teacher until it is done (or ``done(cell, teacher)`` says so)."""
    cell.krc.gravity_compensation = True
    dt_cycle = cell.cycle_ns * 1e-9
    rows = []
    n_max = int(max_seconds / dt_cycle)
    completed = False
    for k in range(n_max):
        m = cell.begin_cycle()
        pose = m.msr_cart_pos.reshape(3, 4)
        twist = cell.tcp_twist()
        hand = teacher.step(dt_cycle, pose[:, 3], twist[:3], pose[:, :3], twist[3:],
                            cell.contact_force, cell.touching)
        out = cell.end_cycle(hand)
        teacher.update_label(out.touching)
        if k % sample_every == 0:
            w = out.ft.wrench(cell.ati_config)
            R = pose[:, :3]
            wb = np.concatenate([R @ w[:3], R @ w[3:]])
            rows.append((out.t_ns * 1e-9, m.msr_jnt_pos, m.msr_cart_pos, w, wb, out.contact_force,
                         teacher.true_phase))
        if teacher.done or (done is not None and done(cell, teacher)):
            completed = True
            break
    return Demonstration(
        t=np.array([r[0] for r in rows]), q=np.array([r[1] for r in rows]),
        tcp_pose=np.array([r[2] for r in rows]), wrench_sensor=np.array([r[3] for r in rows]),
        wrench_base=np.array([r[4] for r in rows]), contact_force=np.array([r[5] for r in rows]),
        true_phase=np.array([r[6] for r in rows], dtype=np.int64), completed=completed,
        dt=sample_every * dt_cycle,
    )
