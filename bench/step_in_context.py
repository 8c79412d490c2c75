"""MuJoCo's step where it runs: in the floor's bare loop and inside the whole cell cycle.

    python bench/step_in_context.py [--cycles 3000] [--trials 3]

bench/lockstep_rtf.py judges a cycle against the floor, bench/sim_step.py's bare loop of
the KRC's law and MuJoCo's step.  This times ``mj_step`` alone (perf_counter_ns around
the call) in four places, alternately, with the arm pressed on a valley plate:

- ``floor``: the bare loop (q, qd -> the KRC's law -> apply -> step);
- ``cell``: the whole cell cycle in command mode (FRI measurement, the remote's command,
  the law, the step, the contacts, the ATI sample), as bench/sim_step.py runs it;
- ``tight``: ``mj_step`` called back to back on the state the cell left;
- ``floor+``: the floor's loop with a whole cycle of the other cell run between its
  steps: the floor's physics, in the cell's company.

and the constraint solver's iterations per step (``solver_niter`` of the first island),
which say whether the physics asked for the same work.  Where the floor's own step costs
more in the cell's company at the same iterations, the rest of the cycle (Python,
Pinocchio, numba code and data) is what it costs: what a bare loop cannot show.
"""

from __future__ import annotations

import argparse
import time

import mujoco

import robot_sim.world.physics as physics
from sim_step import commanded_cycles, law_and_physics, pressed_cell

_ns = time.perf_counter_ns


class TimedStep:
    """``mujoco.mj_step`` with its own time and the solver's iterations added up; stands in
    for the ``mujoco`` module robot_sim.world.physics calls while a timing runs."""

    def __init__(self, only=None):
        self.only = only  # the MjData whose steps count (None: every one)
        self.ns = self.steps = self.iterations = 0

    def mj_step(self, model, data):
        if self.only is not None and data is not self.only:
            return mujoco.mj_step(model, data)
        t = _ns()
        mujoco.mj_step(model, data)
        self.ns += _ns() - t
        self.steps += 1
        self.iterations += int(data.solver_niter[0])

    def __getattr__(self, name):  # the rest of MuJoCo (a lookup more per call, ~0.1 us, out of the timing)
        return getattr(mujoco, name)

    def row(self, name: str) -> str:
        return f"{name:<8} {self.ns / self.steps / 1e3:>10.1f} {self.iterations / self.steps:>11.2f}"


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cycles", type=int, default=3000, help="steps per timing (default 3000)")
    parser.add_argument("--trials", type=int, default=3, help="alternations of the four (default 3)")
    args = parser.parse_args()
    if args.cycles < 1 or args.trials < 1:
        parser.error("--cycles and --trials must be at least 1")

    floor_cell, q0, cmd, _ = pressed_cell()
    floor_cell.place(q0)
    floor = law_and_physics(floor_cell, cmd)
    cell, q0c, cmd_c, stiffness = pressed_cell()
    cell.start()
    cell.place(q0c)
    cell.fri.request_command_mode()
    whole = commanded_cycles(cell, cmd_c, stiffness)
    whole(700)  # quality PERFECT for 500 cycles, then command mode: the arm presses on the plate
    if cell.fri.state != 2:
        raise SystemExit(f"step_in_context.py: the cell did not enter command mode (FRI state {cell.fri.state})")
    floor(700)

    print(f"{'where':<8} {'mj_step us':>10} {'iterations':>11}   (arm pressed on a valley plate, "
          f"{args.cycles} steps a timing)")
    def floor_in_company(k):
        for _ in range(k):
            whole(1)
            floor(1)

    for _ in range(args.trials):
        for name, run, only in (("floor", floor, None), ("cell", whole, None),
                                ("floor+", floor_in_company, floor_cell.sim.data)):
            timed = physics.mujoco = TimedStep(only)
            try:
                run(args.cycles)
            finally:
                physics.mujoco = mujoco
            print(timed.row(name))
        timed, model, data = TimedStep(), cell.sim.model, cell.sim.data
        for _ in range(args.cycles):
            timed.mj_step(model, data)
        print(timed.row("tight"))
        cell.place(q0c)  # the tight loop ran the cell's arm on without its law
        whole(200)


if __name__ == "__main__":
    main()
