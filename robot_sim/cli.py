"""``robot-sim``: run the simulated cell without the services.

    robot-sim demo --world valley --side left --png valley.png --npz demo.npz

``demo`` runs one kinesthetic demonstration by the simulated teacher and
writes a picture (tool path coloured by true phase, positions and forces) and
/ or the recording as ``.npz`` (``states`` = tool position (T, 3),
``forces`` = tared force in base axes (T, 3), ``phases`` = true phase per step,
``dt``), which ``etar learn`` reads.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def cmd_demo(args) -> int:
    from robot_sim.cell import RobotCell
    from robot_sim.demonstration import record_demonstration, settle_and_tare
    from robot_sim.plots import plot_demonstration
    from robot_sim.teacher import DOWN, HoseCouplerTeacher, ValleyTeacher
    from robot_sim.worlds import hose_coupler, valley

    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    if args.world == "valley":
        cell = RobotCell(valley(), seed=args.seed)
        side = -1 if args.side == "left" else 1
        start = np.array([0.68, 0.10 * side, 0.40]) + rng.uniform(-args.spread, args.spread, 3)
        teacher = ValleyTeacher(cell.world.task, start, goal_x=0.42, rng=rng)
        done = None
        names = ["free motion", "sliding along a plate", "sliding along the groove"]
    else:
        cell = RobotCell(hose_coupler(), seed=args.seed)
        start = np.array([0.62, -0.08, 0.36]) + rng.uniform(-args.spread, args.spread, 3)
        teacher = HoseCouplerTeacher(cell.world.task, start, rng=rng)

        def done(c, t):
            return t.phase == 1 and t.rotation_done(c.sim.tcp_rotation())

        names = ["approach", "coupling (turning)"]
    cell.place_tcp(start, DOWN)
    cell.start()
    settle_and_tare(cell)
    demo = record_demonstration(cell, teacher, max_seconds=args.max_seconds, done=done)
    wall = time.perf_counter() - t0
    counts = np.bincount(demo.true_phase).tolist()
    print(f"{args.world} demonstration: {demo.t[-1]:.2f} s simulated in {wall:.2f} s, "
          f"{len(demo.t)} samples at {1 / demo.dt:.0f} Hz, samples per phase {counts}, "
          f"{'completed' if demo.completed else 'NOT completed'}", file=sys.stderr)
    if args.png:
        plot_demonstration(demo, args.png, f"{args.world} demonstration (seed {args.seed})", names)
        print(f"wrote {args.png}", file=sys.stderr)
    if args.npz:
        np.savez(args.npz, states=demo.positions, forces=demo.wrench_base[:, :3], phases=demo.step_phases(),
                 dt=np.float64(demo.dt), tcp_pose=demo.tcp_pose, wrench_sensor=demo.wrench_sensor,
                 torques=demo.wrench_base[:, 3:])
        print(f"wrote {args.npz}", file=sys.stderr)
    return 0 if demo.completed else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="robot-sim", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("demo", help="one kinesthetic demonstration by the simulated teacher")
    p.add_argument("--world", choices=("valley", "hose_coupler"), default="valley")
    p.add_argument("--side", choices=("left", "right"), default="left", help="valley: starting side")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--spread", type=float, default=0.0, help="random start offset per axis, m")
    p.add_argument("--max-seconds", type=float, default=60.0, help="simulated-time limit")
    p.add_argument("--png", help="write a picture of the demonstration here")
    p.add_argument("--npz", help="write the recording here (readable by `etar learn`)")
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
