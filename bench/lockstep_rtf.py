"""Lockstep real-time factor (simulated seconds per wall second), over Zenoh and in one process.

    python bench/lockstep_rtf.py [--scenario scenarios/smoke.yaml] [--transports zenoh,inproc] [--out DIR]

Runs the same scenario (same seed) once per transport, one after the other, and
prints per episode: simulated seconds, wall seconds, their ratio and where a
cycle's wall time goes - the robot's own sections (handing the answers to the
FRI link, the physics step, measuring, encoding, publishing) and the wait for
the cycle's answers (over Zenoh: the round trip robot -> participant(s) -> robot
between processes; in one process: the other nodes' work on the cycle's
messages).  Then a table of both: real-time factor over the episodes, the whole
job's wall time (start-up, learning, report included), the learn stage, and
whether the two runs recorded the same messages (payloads without ``sent_ns``).

Targets (issue 11): in one process >= 5x real time over the episodes, and the
whole job >= 5x faster than over Zenoh lockstep.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

def one(transport: str, scenario: str, out: Path) -> dict:
    from cpuwatch import CpuWatch
    from services.run.options import RunOptions
    from services.run.runner import run
    from services.scenario import load_scenario

    run_id = f"rtf-{transport}-{uuid.uuid4().hex[:6]}"
    watch = CpuWatch(run_id).start() if transport == "zenoh" else None
    t = time.monotonic()
    report = run(load_scenario(scenario).replace("clock", "lockstep"),
                 RunOptions(out=str(out), run_id=run_id, transport=transport),
                 progress=lambda m: print(f"[{transport}] {m}", file=sys.stderr))
    wall = time.monotonic() - t
    cpu = None
    if watch is not None:
        watch.stop()
        cpu = watch.usage(watch.samples[0][0], watch.samples[-1][0])
    return dict(report=report, wall=wall, cpu=cpu, out=out)


def episodes_table(name: str, r: dict) -> dict:
    report = r["report"]
    loops = report["timing"]["robot_loop"]["per_episode"]
    episodes = [("demonstration", i, d) for i, d in enumerate(report["demonstrations"])] + \
               [("reproduction", i, e) for i, e in enumerate(report["reproductions"])]
    sections = list(loops[0]["sections"]) if loops else []
    print(f"\n{name}: scenario {report['scenario']}; {r['wall']:.1f} s wall in all; run directory {r['out']}")
    print(f"{'episode':<16} {'sim s':>6} {'wall s':>7} {'RTF':>6} {'us/cycle':>9}   "
          + " ".join(f"{s:>8}" for s in sections))
    total_sim = total_wall = 0.0
    totals = dict.fromkeys(sections, 0.0)
    cycles_all = 0
    for (kind, index, e), lp in zip(episodes, loops[-len(episodes):]):
        sim, w, cycles = e["sim_seconds"], e["wall_seconds"], lp["cycles"]
        total_sim += sim
        total_wall += w
        cycles_all += cycles
        for s in sections:
            totals[s] += lp["sections"][s]["mean_us"] * cycles
        print(f"{kind[:12] + ' ' + str(index):<16} {sim:6.1f} {w:7.1f} {sim / w:6.2f} "
              f"{w / max(cycles, 1) * 1e6:9.0f}   " + " ".join(f"{lp['sections'][s]['mean_us']:8.0f}"
                                                           for s in sections))
    mean = {s: totals[s] / max(cycles_all, 1) for s in sections}
    per_cycle = total_wall / max(cycles_all, 1) * 1e6
    print(f"{'all episodes':<16} {total_sim:6.1f} {total_wall:7.1f} {total_sim / total_wall:6.2f} {per_cycle:9.0f}   "
          + " ".join(f"{mean[s]:8.0f}" for s in sections))
    if r["cpu"]:
        print("CPU over the run (% of one CPU): " + ", ".join(f"{k} {v:.0f}" for k, v in sorted(r["cpu"].items())
                                                             if k != "seconds"))
    return dict(sim=total_sim, episode_wall=total_wall, rtf=total_sim / total_wall, per_cycle_us=per_cycle,
                own_us=sum(v for k, v in mean.items() if k != "wait"), wait_us=mean.get("wait", 0.0),
                wall=r["wall"], learn=report["learning"].get("seconds"),
                phases=report["summary"]["phases_chosen"], successes=report["summary"]["successes"],
                reproductions=report["summary"]["reproductions"],
                accuracy=report["summary"]["online_phase_accuracy"])


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default=str(ROOT / "scenarios" / "smoke.yaml"))
    parser.add_argument("--transports", default="zenoh,inproc", help="comma-separated, run in this order")
    parser.add_argument("--out", help="folder for the runs (default: a temporary one)")
    args = parser.parse_args()
    transports = [t.strip() for t in args.transports.split(",") if t.strip()]
    base = Path(args.out or tempfile.mkdtemp(prefix="lockstep_rtf-"))
    runs = {t: one(t, args.scenario, base / t) for t in transports}
    for t, r in runs.items():
        if r["report"]["error"]:
            print(f"{t}: run failed: {r['report']['error']}")
            return 1
    rows = {t: episodes_table(t, r) for t, r in runs.items()}
    print(f"\n{'transport':<10} {'sim s':>7} {'episodes s':>11} {'RTF':>6} {'us/cycle':>9} {'own':>6} {'wait':>6} "
          f"{'job s':>7} {'learn s':>8}  phases  goal      accuracy")
    for t, row in rows.items():
        learn = "-" if row["learn"] is None else f"{row['learn']:.1f}"
        acc = "-" if row["accuracy"] is None else f"{row['accuracy']:.4f}"
        print(f"{t:<10} {row['sim']:7.1f} {row['episode_wall']:11.1f} {row['rtf']:6.2f} {row['per_cycle_us']:9.0f} "
              f"{row['own_us']:6.0f} {row['wait_us']:6.0f} {row['wall']:7.1f} {learn:>8}  {row['phases']!s:>6}  "
              f"{row['successes']}/{row['reproductions']:<6}  {acc}")
    if {"zenoh", "inproc"} <= set(rows):
        z, i = rows["zenoh"], rows["inproc"]
        from services.recordings.reader import recorded_content

        same = recorded_content(runs["zenoh"]["out"]) == recorded_content(runs["inproc"]["out"])
        print(f"in-process vs Zenoh: {i['rtf'] / z['rtf']:.1f}x the real-time factor over the episodes, "
              f"the whole job {z['wall'] / i['wall']:.1f}x faster; recordings "
              f"{'the same' if same else 'DIFFERENT'} (payloads without sent_ns)")
        print(f"targets: in-process >= 5x real time over the episodes ({i['rtf']:.2f}x), the whole job >= 5x "
              f"faster than Zenoh lockstep ({z['wall'] / i['wall']:.1f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
