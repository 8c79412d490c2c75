"""What a reproduction cycle in one process is made of: its compiled parts timed in the run.

    python bench/cycle_budget.py [--reproductions 4] [--engine fused] [--out DIR]

Runs the valley's reproduce stage in one process with the stored model
(``scenarios/models/valley.json``, the valley's reproduction settings, its seed) and times,
inside that run, every call of the pieces no engine can leave out: the compiled kernels of
the cell (the KRC's law and MuJoCo's steps, the measurement's kinematics, the sensing of
the tool's wrench and contacts, the ATI sample), of the commander (the policy) and of the
KRC's command checks, then orjson writing every message's JSON and the pipe to the MCAP
writer's helper process.  The rest of the cycle is the nodes' and the engine's Python.
Beside it, in the same process, the floor ``bench/lockstep_rtf.py`` divides by (the KRC's
law and MuJoCo's step with the arm pressed on a plate, ``bench/sim_step.py``).

Prints microseconds per 1 ms cycle for each part, what a cycle within 5x the floor would
leave for everything else, and the physics of the run against the floor's.  Then the same
cycle node by node: the time inside each method the fused engine calls a node's work
through (``services.transport.fused``: the robot's measurement and close, the commander's,
the sensor's, the estimator's, the recorder's), their kernels included, and the engine's
own share (the cycle engine, the hand-overs between the nodes): which node's Python a
compiled cycle would have to take over, and how much of it.  Each timed call costs a
timer's pair of clock reads, measured and taken off.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections import Counter
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from node_costs import timed  # noqa: E402  (bench/, beside this script)
from services.transport.carriers import ENGINES  # noqa: E402

# (label, module, global name): kernels called through module globals at call time
KERNELS = (
    ("the KRC's law and MuJoCo's steps", "robot_sim.cell", "_PHYSICS_CYCLE"),
    ("the measurement's kinematics", "robot_sim.cell", "_MEASURE"),
    ("sensing: the tool's wrench, joint torques", "robot_sim.world.physics", "_sensed"),
    ("sensing: the tip's contacts", "robot_sim.world.physics", "_tip_contacts"),
    ("the ATI sample", "robot_sim.ati.sensor", "_sample"),
    ("the ATI sample and ft/wrench's bytes", "services.nodes.ft_sensor", "_RECORD"),
    ("the KRC's command checks", "robot_sim.krc.packets", "_NUMBERS"),
    ("orjson: every message's JSON", "services.runtime.messages", "_dumps"),
)
POLICY = "the commander's policy"
# (label, module, class, methods): what the fused engine calls a node's per-cycle work through
NODE_WORK = (
    ("robot: measure, robot/state", "services.nodes.robot", "RobotNode", ("measure_state",)),
    ("robot: the truth, robot/contact", "services.nodes.robot", "RobotNode", ("measure_contact",)),
    ("robot: close (answers, KRC, step, judge)", "services.nodes.robot", "RobotNode", ("apply",)),
    ("commander: answer, robot/command", "services.nodes.impedance_commander", "ImpedanceCommanderNode",
     ("take_state", "take_phase", "give_up", "deliver")),
    ("sensor: the ATI sample, ft/wrench", "services.nodes.ft_sensor", "FtSensorNode", ("sample",)),
    ("estimator (100 Hz)", "services.nodes.phase_estimator", "PhaseEstimatorNode", ("take_state", "take_wrench")),
    ("teacher", "services.nodes.teacher", "TeacherNode", ("take_state", "take_contact")),
    ("recorder: the hand-over", "services.nodes.recorder", "RecorderNode", ("take",)),
)
PIPE = "the pipe to the MCAP writer"


class Timers:
    """Per label: calls and nanoseconds inside them (``bench/node_costs.py``'s timer)."""

    def __init__(self):
        self.ns: Counter = Counter()
        self.calls: Counter = Counter()

    def wrap(self, label: str, fn):
        return timed(fn, label, self.ns, self.calls)


def timer_cost_ns(n: int = 200_000) -> float:
    """ns a timed call adds inside its own interval (a wrapped no-op's)."""
    probe = Timers()
    nop = probe.wrap("nop", abs)
    best = float("inf")
    for _ in range(3):
        probe.ns["nop"] = 0
        for _ in range(n):
            nop(1)
        best = min(best, probe.ns["nop"] / n)
    return best


def install(timers: Timers) -> None:
    import importlib

    import etar.policy_kernel as policy_kernel
    from services.recordings import offload

    for label, module, name in KERNELS:
        mod = importlib.import_module(module)
        fn = getattr(mod, name)
        if fn is None:
            raise SystemExit(f"{module}.{name} is not compiled on this machine: nothing to time")
        setattr(mod, name, timers.wrap(label, fn))
    make_policy_kernel = policy_kernel._step_entry
    policy_kernel._step_entry = lambda: timers.wrap(POLICY, make_policy_kernel())
    send = offload.WriterProcess._send
    offload.WriterProcess._send = timers.wrap(PIPE, send)
    for label, module, cls_name, methods in NODE_WORK:
        cls = getattr(importlib.import_module(module), cls_name)
        for name in methods:
            setattr(cls, name, timers.wrap(label, getattr(cls, name)))


def reproduce_only(n: int, out: Path) -> Path:
    """The valley's reproduce stage alone with the stored model, as a scenario file."""
    valley = yaml.safe_load((ROOT / "scenarios" / "valley.yaml").read_text())
    (stage,) = [s for s in valley["stages"] if "reproduce" in s]
    stage["reproduce"]["count"] = n
    valley.update(name="cycle_budget", model=str(ROOT / "scenarios" / "models" / "valley.json"), stages=[stage])
    path = out / "cycle_budget.yaml"
    path.write_text(yaml.safe_dump(valley, sort_keys=False))
    return path


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--reproductions", type=int, default=4, help="reproductions of the valley (default 4)")
    parser.add_argument("--engine", default="fused", choices=ENGINES, help="the in-process engine")
    parser.add_argument("--out", type=Path, default=None, help="keep the run here (default: a temporary folder)")
    args = parser.parse_args()
    if args.reproductions < 1:
        parser.error(f"--reproductions must be at least 1, got {args.reproductions}")

    from services.run.options import RunOptions
    from services.run.runner import run
    from services.scenario import load_scenario
    from sim_step import physical_floor_us

    floor = min(physical_floor_us(5000) for _ in range(3))
    overhead = timer_cost_ns()
    timers = Timers()
    install(timers)
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp) / "run"
        out.mkdir(parents=True, exist_ok=True)
        scenario = load_scenario(str(reproduce_only(args.reproductions, out)))
        report = run(scenario, RunOptions(out=str(out / "run"), run_id="cycle-budget", transport="inproc",
                                          engine=args.engine, figures=False), progress=lambda line: None)
    if report["error"]:
        raise SystemExit(f"the run failed: {report['error']}")
    untimed = [label for label in [k[0] for k in KERNELS] + [POLICY, PIPE] if not timers.calls[label]]
    if untimed:  # the code no longer calls it where this bench looks: a figure of 0 would mislead
        raise SystemExit(f"never called in the run, so not timed: {', '.join(untimed)}")
    episodes = report["timing"]["robot_loop"]["per_episode"]
    cycles = sum(e["cycles"] for e in episodes)
    wall = sum(r["wall_seconds"] for r in report["reproductions"])
    cycle_us = wall / cycles * 1e6
    floor_after = min(physical_floor_us(5000) for _ in range(3))
    floor = min(floor, floor_after)

    print(f"the valley's reproduce stage in one process ({args.engine}): {len(report['reproductions'])} "
          f"reproductions, {cycles} cycles, {wall:.1f} s: {cycle_us:.1f} us a cycle (timers included)")
    print(f"a timer's own cost {overhead:.0f} ns a call, taken off below\n")
    # the parts per cycle stepped (the law's calls: one a cycle, the settles before the
    # episodes included), the whole cycle per cycle of the episodes
    stepped = timers.calls[KERNELS[0][0]]
    print(f"{'part':<44} {'calls/cycle':>11} {'us/call':>8} {'us/cycle':>9} {'x floor':>8}")
    parts = 0.0
    for label in [k[0] for k in KERNELS] + [POLICY, PIPE]:
        calls = timers.calls.get(label, 0)
        ns = timers.ns.get(label, 0) - overhead * calls
        per_cycle = ns / stepped / 1e3
        parts += per_cycle
        print(f"{label:<44} {calls / stepped:11.2f} {ns / max(calls, 1) / 1e3:8.2f} {per_cycle:9.2f} "
              f"{per_cycle / floor:8.2f}")
    rest = cycle_us - parts
    print(f"{'the parts above':<44} {'':11} {'':8} {parts:9.2f} {parts / floor:8.2f}")
    print(f"{'the rest: the nodes and the engine (Python)':<44} {'':11} {'':8} {rest:9.2f} {rest / floor:8.2f}")
    print(f"\nthe floor (law and step from Python, arm pressed on a plate): {floor:.1f} us a cycle")
    physics = (timers.ns[KERNELS[0][0]] - overhead * stepped) / stepped / 1e3
    print(f"the run's own law and steps (compiled, the valley's contacts): {physics:.1f} us a cycle = "
          f"{physics / floor:.2f}x the floor")
    budget = 5 * floor
    print(f"a cycle within 5x the floor: {budget:.1f} us; the parts above take {parts:.1f} of it, "
          f"leaving {budget - parts:.1f} us for the nodes and the engine (now {rest:.1f})")
    print(f"15x real time: {1000 / 15:.1f} us a cycle; leaving {1000 / 15 - parts:.1f} us beyond the parts")
    by_node(timers, overhead, stepped, cycle_us, floor)


def by_node(timers: Timers, overhead: float, stepped: int, cycle_us: float, floor: float) -> None:
    """The cycle node by node, each with its kernels, and the engine's share (the rest)."""
    print(f"\n{'the cycle by node (kernels included)':<44} {'calls/cycle':>11} {'us/call':>8} {'us/cycle':>9} "
          f"{'x floor':>8}")
    total = 0.0
    for label, *_ in NODE_WORK:
        calls = timers.calls.get(label, 0)
        if not calls:
            continue  # (the teacher in a reproduction)
        ns = timers.ns[label] - overhead * calls
        per_cycle = ns / stepped / 1e3
        total += per_cycle
        print(f"{label:<44} {calls / stepped:11.2f} {ns / calls / 1e3:8.2f} {per_cycle:9.2f} {per_cycle / floor:8.2f}")
    rest = cycle_us - total
    print(f"{'the engines: cycle, hand-overs, timing':<44} {'':11} {'':8} {rest:9.2f} {rest / floor:8.2f}")


if __name__ == "__main__":
    main()
