"""Lockstep real-time factor (simulated seconds per wall second) of the valley loop, per stage.

    python bench/lockstep_rtf.py [--scenario scenarios/smoke.yaml] [--out DIR]

Runs the scenario on the lockstep clock (every participant answers every
cycle; the commander answers every FRI measurement) and prints, per episode,
simulated seconds, wall seconds and their ratio, and where a cycle's wall time
goes: the robot's own sections (handing the answers to the FRI link, the
physics step, measuring, encoding, publishing) and the wait for the cycle's
answers, i.e. the round trip robot -> participant(s) -> robot over Zenoh.
Every tenth cycle of a reproduction the commander also waits for the estimate,
which waits for the sensor: robot -> sensor -> estimator -> commander -> robot.
The learn stage is wall time without simulated time and is listed apart.

Target (issue "Timing you can trust"): >= 5x real time.  The last line says
what bounds it: with one Zenoh round trip per 1 ms cycle the factor cannot
exceed 1 ms / (robot's own work + the round trip), whatever the rest costs.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default=str(ROOT / "scenarios" / "smoke.yaml"))
    parser.add_argument("--out", help="run directory (default: a temporary one)")
    args = parser.parse_args()

    import uuid

    from cpuwatch import CpuWatch
    from services.runner import RunOptions, run

    out = args.out or tempfile.mkdtemp(prefix="lockstep_rtf-")
    run_id = f"rtf-{uuid.uuid4().hex[:8]}"
    watch = CpuWatch(run_id).start()
    t = time.monotonic()
    report = run(RunOptions(scenario=args.scenario, out=out, clock="lockstep", run_id=run_id),
                 progress=lambda m: print(m, file=sys.stderr))
    wall = time.monotonic() - t
    watch.stop()
    if report["error"]:
        print(f"run failed: {report['error']}")
        return 1
    loops = report["timing"]["robot_loop"]["per_episode"]
    episodes = [("demonstration", d) for d in report["demonstrations"]] + \
               [("reproduction", r) for r in report["reproductions"]]
    sections = list(loops[0]["sections"]) if loops else []
    print(f"lockstep, scenario {report['scenario']} ({args.scenario}); {wall:.1f} s wall in all; run directory {out}")
    head = f"{'episode':<16} {'sim s':>6} {'wall s':>7} {'RTF':>6} {'us/cycle':>9}   " + \
           " ".join(f"{s:>8}" for s in sections)
    print(head)
    total_sim = total_wall = 0.0
    totals = dict.fromkeys(sections, 0.0)
    cycles_all = 0
    for (kind, e), lp in zip(episodes, loops[-len(episodes):]):
        sim, w = e["sim_seconds"], e["wall_seconds"]
        cycles = lp["cycles"]
        total_sim += sim
        total_wall += w
        cycles_all += cycles
        for s in sections:
            totals[s] += lp["sections"][s]["mean_us"] * cycles
        index = sum(1 for k, _ in episodes[:episodes.index((kind, e))] if k == kind)
        print(f"{kind[:12] + ' ' + str(index):<16} "
              f"{sim:6.1f} {w:7.1f} {sim / w:6.2f} {w / max(cycles, 1) * 1e6:9.0f}   "
              + " ".join(f"{lp['sections'][s]['mean_us']:8.0f}" for s in sections))
    mean = {s: totals[s] / max(cycles_all, 1) for s in sections}
    per_cycle = total_wall / max(cycles_all, 1) * 1e6
    print(f"{'all episodes':<16} {total_sim:6.1f} {total_wall:7.1f} {total_sim / total_wall:6.2f} {per_cycle:9.0f}   "
          + " ".join(f"{mean[s]:8.0f}" for s in sections))
    sel = report["learning"].get("selection") or {}
    learn_wall = wall - total_wall
    print(f"outside the episodes (start-up, learning {sel.get('best', '-')} phases, taring, settling, report): "
          f"{learn_wall:.1f} s wall; whole run {total_sim / wall:.2f} x real time")
    own = sum(v for k, v in mean.items() if k != "wait")
    print(f"per cycle: robot's own work {own:.0f} us + waiting for the answers {mean['wait']:.0f} us "
          f"(+ {per_cycle - own - mean['wait']:.0f} us bookkeeping) = {per_cycle:.0f} us -> "
          f"{1000 / per_cycle:.2f} x real time; without any wait the robot alone would run "
          f"{1000 / own:.1f} x; 5 x needs <= 200 us per cycle in all")
    cpu = watch.usage(watch.samples[0][0], watch.samples[-1][0])
    if cpu:
        print("CPU over the run (% of one CPU): " + ", ".join(f"{k} {v:.0f}" for k, v in sorted(cpu.items())
                                                             if k != "seconds"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
