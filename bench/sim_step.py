"""Cost of one simulated FRI cycle (1 ms of physics) on this machine.

    python bench/sim_step.py [--cycles 5000] [--no-malloc-count]

Times, per 1 ms step: MuJoCo alone; MuJoCo + the KRC's Cartesian impedance law
(Pinocchio); and the whole cell cycle (FRI link bookkeeping, impedance law,
physics, ATI sensor), arm pressed against a valley plate (one contact).
Target: under 100 us per step with the impedance law, i.e. the
simulation runs at least 10x faster than real time.

Then the control step alone (read q, qd; krc.compute; apply; step) in each of
the KRC's modes: us per step, what tracemalloc sees allocated per step (net
growth, and the largest transient of a single step), and C-level allocations
per step: a malloc counter compiled here with gcc is preloaded into a child
process run with PYTHONMALLOC=malloc, so that Python objects, numpy arrays,
numba's runtime and C++ (Pinocchio, eigenpy, MuJoCo) all go through it
(bench/allocation.py).  ROBOT_SIM_PINOCCHIO_INPLACE=0 runs the same steps
through Pinocchio's bindings instead of robot_sim.arm._pinocchio_inplace.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pinocchio as pin

from robot_sim.cell import RobotCell
from robot_sim.krc.packets import CommandPacket
from robot_sim.arm.kinematics import PINOCCHIO_INPLACE, PINOCCHIO_INPLACE_MISSING
from robot_sim.krc.law import ImpedanceCommand, pose_to_cart_pos
from robot_sim.world.teacher import DOWN
from robot_sim.world.tasks import Valley, valley


def per_step(fn, cycles):
    fn(200)  # warm up
    t = time.perf_counter()
    fn(cycles)
    return (time.perf_counter() - t) / cycles * 1e6


def pressed_cell(world=None):
    """A valley cell (``world``: another valley's, e.g. a contact candidate's) with the tool
    2 mm over the left plate, and a Cartesian impedance command 1 cm into it: (cell, q0,
    command, stiffness)."""
    world = world or valley(Valley())
    g = world.task
    cell = RobotCell(world, seed=0)
    n = g.plate_normal(-1)
    y = -0.08
    contact = np.array([0.6, y, g.surface_z(y)]) + n * cell.kin.description.tool.tip_radius
    q0 = cell.place_tcp(contact + 0.002 * n, DOWN)
    setpoint = pin.SE3(DOWN, contact - 0.01 * n)
    stiffness = np.array([1000.0] * 3 + [150.0] * 3)
    cmd = ImpedanceCommand(pose_to_cart_pos(setpoint), stiffness, np.full(6, 0.7), np.zeros(6))
    return cell, q0, cmd, stiffness


def law_and_physics(cell, cmd):
    """The bare loop of the cell's physics: k times (q, qd -> the KRC's law -> MuJoCo's step)."""
    sim, krc = cell.sim, cell.krc
    q, qd = np.empty(7), np.empty(7)

    def steps(k):
        for _ in range(k):
            sim.joint_positions(q)
            sim.joint_velocities(qd)
            tau = krc.compute(q, qd, cmd, hold=False)
            sim.apply(tau)
            sim.step()
    return steps


def physical_floor_us(cycles: int = 5000, world=None) -> float:
    """us per 1 ms cycle of the bare loop (law and physics, arm pressed on a plate): the
    floor a whole cycle is measured against (bench/lockstep_rtf.py)."""
    cell, q0, cmd, _ = pressed_cell(world)
    cell.place(q0)
    return per_step(law_and_physics(cell, cmd), cycles) * cell.sim.substeps


def commanded_cycles(cell, cmd, stiffness):
    """k whole cell cycles (FRI measurement, the remote's command, the KRC's law, MuJoCo's
    step, the ATI sample), the command answered 0.1 ms into each."""

    def cycles(k):
        for _ in range(k):
            m = cell.begin_cycle()
            cell.receive(CommandPacket(m.seq, cmd.cart_pos, stiffness, np.full(6, 0.7)), m.stamp_ns + 100_000)
            cell.end_cycle()
    return cycles


def whole_cell_cycle(cycles: int = 5000):
    """(us per whole cell cycle in command mode with the arm pressed on a plate, the cell)."""
    cell, q0, cmd, stiffness = pressed_cell()
    cell.start()
    cell.place(q0)
    cell.fri.request_command_mode()
    whole_cycle = commanded_cycles(cell, cmd, stiffness)
    whole_cycle(700)  # quality PERFECT for 500 cycles, then CMD: the arm presses on the plate
    assert cell.fri.state == 2, cell.fri.state
    return per_step(whole_cycle, cycles), cell


# -------------------------------------------------------------------- main


def main():
    # bench/allocation.py, beside this script (which other benches and the tests import for
    # its cells and timings alone)
    from allocation import MallocCountUnavailable, control_steps, count_mallocs, traced_allocation

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cycles", type=int, default=5000)
    parser.add_argument("--no-malloc-count", action="store_true", help="skip the C-level allocation count")
    args = parser.parse_args()
    cell, q0, cmd, stiffness = pressed_cell()
    sim = cell.sim

    def physics_only(k):
        for _ in range(k):
            sim.apply(np.zeros(7))
            sim.step()

    with_law = law_and_physics(cell, cmd)
    cell.start()
    cell.place(q0)
    t_phys = per_step(physics_only, args.cycles)
    cell.place(q0)
    t_law = per_step(with_law, args.cycles)
    t_cell, pressing = whole_cell_cycle(args.cycles)
    touching = pressing.sim.touching()
    print(f"{'what':<52} {'us/step':>8} {'x real time':>12}")
    for name, t in (("MuJoCo step alone (arm + contact)", t_phys),
                    ("+ KRC Cartesian impedance law (Pinocchio)", t_law),
                    ("whole cell cycle: FRI + law + physics + ATI", t_cell)):
        print(f"{name:<52} {t:>8.1f} {1000.0 / t:>12.1f}")
    print(f"contact during the run: {touching}; target: < 100 us per step with the law")

    cycles = min(args.cycles, 2000)
    counts, why = None, "skipped"
    if not args.no_malloc_count:
        try:
            counts = count_mallocs(cycles)
        except MallocCountUnavailable as e:
            why = str(e)
    print(f"\ncontrol step (q, qd -> krc.compute -> apply -> step), {cycles} steps per mode; Pinocchio update: "
          + ("robot_sim.arm._pinocchio_inplace" if PINOCCHIO_INPLACE else f"the bindings ({PINOCCHIO_INPLACE_MISSING})"))
    print(f"{'KRC mode':<22} {'us/step':>8} {'traced B/step':>14} {'peak B/step':>12} {'mallocs/step':>13} "
          f"{'malloc B/step':>14}")
    for name, (step, _) in control_steps().items():
        t = per_step(lambda k, step=step: [step() for _ in range(k)], cycles)
        growth, peak = traced_allocation(step, cycles)
        c, b = (x / cycles for x in counts[name]) if counts else (float("nan"), float("nan"))
        print(f"{name:<22} {t:>8.1f} {growth / cycles:>14.1f} {peak:>12d} {c:>13.2f} {b:>14.1f}")
    print("traced: tracemalloc (Python objects, numpy data, numba's runtime); peak: the largest transient of one "
          "step;\nmallocs: every C-level allocation in the process (bench/allocation.py: PYTHONMALLOC=malloc, "
          "counter preloaded)" + (f" -- not measured: {why}" if counts is None else ""))


if __name__ == "__main__":
    main()
