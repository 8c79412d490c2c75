"""What the cell's per-cycle numba kernels cost per call in a running cell: through
numba's dispatcher, and as machine code (``kernel_plumbing.addresses.entry``, what the cell does).

    python bench/dispatch_cost.py [--scenario scenarios/smoke.yaml] [--ways dispatcher,entry]

Runs the scenario in one process once per way (the same seed; no figures), each kernel
call of the cell (its measurement; its physics cycle: the KRC's law and MuJoCo's
steps), the physics' sensing, the ATI sensor and the valley teacher timed alone, and
prints per kernel the calls per FRI cycle and the mean microseconds per call, then the
time per cycle of all.
A loop of calls would measure them hot, which a cycle never sees: between two calls of
a kernel the rest of the cycle (Python, numpy, MuJoCo, Pinocchio, the other nodes) has
pushed the dispatcher's code and data out of the caches.  Both ways call the same
compiled code, so the recordings are the same.

Measured 2026-12-03 (smoke, this 2-core VM): see docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import robot_sim.ati.sensor as ati  # noqa: E402
import robot_sim.cell as cell  # noqa: E402
import robot_sim.world.physics as physics  # noqa: E402
import robot_sim.world.teacher as teacher  # noqa: E402
from node_costs import timed  # noqa: E402  (bench/, beside this script)

# (module, the name the cell calls, the dispatcher it is the machine code of)
KERNELS = (
    (cell, "_MEASURE", cell._measure_at),
    (cell, "_PHYSICS_CYCLE", cell._physics_cycle_at),
    (teacher, "_VALLEY_STEP", teacher._valley_step_at),
    (physics, "_sensed", physics._sensed_at),
    (ati, "_sample", ati._sample_at),
)


def run(scenario: str, way: str, out: Path) -> tuple[Counter, Counter, int, float]:
    from services.cli import bench as bench_cli
    from services.runtime import cycle

    totals, calls = Counter(), Counter()
    originals = {}
    for module, name, dispatcher in KERNELS:
        originals[module, name] = getattr(module, name)
        setattr(module, name, timed(dispatcher if way == "dispatcher" else getattr(module, name), name, totals, calls))
    open_cycle = cycle.CycleEngine._open
    opened = Counter()
    cycle.CycleEngine._open = timed(open_cycle, "cycles", Counter(), opened)
    t = time.perf_counter()
    try:
        code = bench_cli.main(["run", scenario, "--transport", "inproc", "--out", str(out), "--no-figures"])
    finally:
        cycle.CycleEngine._open = open_cycle
        for (module, name), f in originals.items():
            setattr(module, name, f)
    if code:
        raise SystemExit(f"the {way} run failed (exit {code})")
    return totals, calls, opened["cycles"], time.perf_counter() - t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--scenario", default="scenarios/smoke.yaml", help="scenario run in one process per way")
    ap.add_argument("--ways", default="dispatcher,entry", help="comma-separated, run in this order")
    args = ap.parse_args(argv)
    ways = args.ways.split(",")
    if not ways or any(w not in ("dispatcher", "entry") for w in ways):
        ap.error(f"--ways: dispatcher and/or entry, got {args.ways!r}")
    if not Path(args.scenario).is_file():
        ap.error(f"--scenario {args.scenario}: no such file")
    results = {}
    with tempfile.TemporaryDirectory(prefix="dispatch_cost-") as tmp:
        for way in ways:
            results[way] = run(args.scenario, way, Path(tmp) / way)
    print(f"\nthe cell's kernels in a running cell ({args.scenario}, one process): mean us per call")
    names = [name for _, name, _ in KERNELS]
    print(f"{'kernel':16s} {'calls/cycle':>11s} " + " ".join(f"{w:>11s}" for w in ways))
    for name in names:
        if not any(results[w][1][name] for w in ways):
            continue
        cycles = results[ways[0]][2]
        row = " ".join(f"{results[w][0][name] / max(results[w][1][name], 1) / 1e3:11.2f}" for w in ways)
        print(f"{name:16s} {results[ways[0]][1][name] / cycles:11.2f} {row}")
    row = " ".join(f"{sum(results[w][0].values()) / results[w][2] / 1e3:11.2f}" for w in ways)
    print(f"{'all, per cycle':16s} {'':11s} {row}")
    row = " ".join(f"{results[w][3]:10.1f}s" for w in ways)
    print(f"{'whole run':16s} {'':11s} {row}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
