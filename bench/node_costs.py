"""Where a cycle goes in one process, node by node: the wall time of each subscription
handler and of the robot's two halves of the FRI cycle, per cycle.

    python bench/node_costs.py [--scenario scenarios/smoke.yaml]

Runs the scenario with the in-process transport (its seed, no figures) and times every
handler the bus calls, as (node, topic), and the robot's open_cycle (measure, publish)
and close_cycle (the answers, the KRC, the physics step); prints microseconds per FRI
cycle of the run (settling included), the handler's calls per cycle, and the total.
The timer costs about 0.1 us a call.  Run it in two checkouts one after the other to see
what a change did: this VM's speed drifts by tens of percent within a day.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def timed(handler, key, totals: Counter, calls: Counter):
    clock = time.perf_counter_ns

    def call(*args):
        t = clock()
        try:
            return handler(*args)
        finally:
            totals[key] += clock() - t
            calls[key] += 1

    return call


def measure(scenario: str, out: Path) -> tuple[Counter, Counter, int]:
    from services.cli import bench as bench_cli
    from services.runtime import cycle
    from services.transport import inproc

    totals, calls = Counter(), Counter()
    attach, open_cycle, close_cycle = inproc.InProcessBus.attach, cycle.CycleEngine._open, cycle.CycleEngine._close

    def timed_attach(bus, node):
        node.subscriptions = [dataclasses.replace(s, handler=timed(s.handler, (node.name, s.topic), totals, calls))
                              for s in node.subscriptions]
        attach(bus, node)

    inproc.InProcessBus.attach = timed_attach
    cycle.CycleEngine._open = timed(open_cycle, ("robot", "open_cycle"), totals, calls)
    cycle.CycleEngine._close = timed(close_cycle, ("robot", "close_cycle"), totals, calls)
    try:
        code = bench_cli.main(["run", scenario, "--transport", "inproc", "--out", str(out), "--no-figures"])
    finally:
        inproc.InProcessBus.attach, cycle.CycleEngine._open, cycle.CycleEngine._close = attach, open_cycle, close_cycle
    if code:
        raise SystemExit(f"the run failed (exit {code})")
    return totals, calls, calls["robot", "open_cycle"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--scenario", default="scenarios/smoke.yaml", help="scenario run in one process")
    args = ap.parse_args(argv)
    if not Path(args.scenario).is_file():
        ap.error(f"--scenario {args.scenario}: no such file")
    with tempfile.TemporaryDirectory(prefix="node_costs-") as tmp:
        totals, calls, cycles = measure(args.scenario, Path(tmp) / "run")
    if not cycles:
        raise SystemExit("no FRI cycle ran")
    print(f"\n{args.scenario} in one process: {cycles} FRI cycles; wall us per cycle")
    print(f"{'us/cycle':>9s}  {'node':22s} {'topic or part':22s} calls/cycle")
    for (node, topic), ns in sorted(totals.items(), key=lambda kv: -kv[1]):
        print(f"{ns / cycles / 1e3:9.2f}  {node:22s} {topic:22s} {calls[node, topic] / cycles:.2f}")
    print(f"{sum(totals.values()) / cycles / 1e3:9.2f}  all")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
