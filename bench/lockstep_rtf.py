"""Lockstep real-time factor (simulated seconds per wall second), over Zenoh and in one process.

    python bench/lockstep_rtf.py [--scenario scenarios/valley.yaml] [--transports zenoh,inproc] [--out DIR]

``--transports``: zenoh, inproc (one process, its default engine: fused), or inproc:ENGINE
(inproc:fused, inproc:per-message: services.transport.carriers.ENGINES), e.g.
``--transports inproc:per-message,inproc:fused`` to put the two engines side by side.

Runs the same scenario (same seed) once per transport, one after the other, and
prints per episode: simulated seconds, wall seconds, their ratio and where a
cycle's wall time goes - the robot's own sections (handing the answers to the
FRI link, the physics step, measuring, encoding, publishing) and the wait for
the cycle's answers (over Zenoh: the round trip robot -> participant(s) -> robot
between processes; in one process: the other nodes' work on the cycle's
messages; fused: the other nodes' work on the cycle, the recorder's hand-over included).
Then a table of all: real-time factor over the episodes, the whole job's wall time
(start-up, learning, report included), the learn stage, and whether each run recorded
the same messages as the first (payloads without ``sent_ns``).

Then the bare loop of the same physics (MuJoCo's step and the KRC's law alone,
``bench/sim_step.py``) and each transport's cycle as a multiple of it: a figure that
holds on any machine, where real-time factors do not.

Guard: the in-process cycle (the first in-process run's, with its default engine when
there is one) may cost at most 1.5 times the multiple of the floor that docs/benchmarks.md
states (its line "cycle-to-floor ratio N"); above that the bench says so and exits 3, so
that a change cannot quietly lose the speed.

Targets: in one process >= 15x real time over the valley's episodes, the whole job
<= 45 s and the cycle within 5x of the floor; over Zenoh lockstep >= 1x.
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
BENCHMARKS = ROOT / "docs" / "benchmarks.md"
STATED = re.compile(r"cycle-to-floor ratio (\d+(?:\.\d+)?)")
GUARD_MARGIN = 1.5


def stated_ratio() -> float:
    """The in-process cycle's multiple of the floor that docs/benchmarks.md states."""
    found = STATED.search(BENCHMARKS.read_text())
    if not found:
        raise SystemExit(f"{BENCHMARKS}: no line says 'cycle-to-floor ratio N': the guard has nothing to hold to")
    return float(found.group(1))


def guard_failure(ratio: float, stated: float) -> str | None:
    """Why the tree fails the guard (its cycle over GUARD_MARGIN x the stated multiple of
    the floor), or None."""
    if ratio > GUARD_MARGIN * stated:
        return (f"GUARD FAILED: the in-process cycle costs {ratio:.1f}x the floor, more than {GUARD_MARGIN} x the "
                f"{stated}x that {BENCHMARKS.relative_to(ROOT)} states: this tree has lost speed")
    return None


def one(way: str, scenario: str, out: Path) -> dict:
    """``way``: zenoh, inproc or inproc:ENGINE."""
    from cpuwatch import CpuWatch
    from services.run.options import RunOptions
    from services.run.runner import run
    from services.scenario import load_scenario

    transport, _, engine = way.partition(":")
    run_id = f"rtf-{transport}-{uuid.uuid4().hex[:6]}"
    watch = CpuWatch(run_id).start() if transport == "zenoh" else None
    t = time.monotonic()
    report = run(load_scenario(scenario).replace("clock", "lockstep"),
                 RunOptions(out=str(out), run_id=run_id, transport=transport, engine=engine or None),
                 progress=lambda m: print(f"[{way}] {m}", file=sys.stderr))
    wall = time.monotonic() - t
    cpu = episode_cpu = None
    if watch is not None:
        watch.stop()
        # up to the last sample with the services alive: one taken after they ended would
        # put their time under "other"
        alive = [sample for sample in watch.samples if len(sample[2]) > 1] or watch.samples
        cpu = watch.usage(alive[0][0], alive[-1][0])
        episodes = len(report["demonstrations"]) + len(report["reproductions"])
        loops = report["timing"]["robot_loop"]["per_episode"]
        episode_cpu = cpu_within_episodes(watch, loops[len(loops) - episodes:])  # not the settles before them
    return dict(report=report, wall=wall, cpu=cpu, episode_cpu=episode_cpu, out=out)


def cpu_within_episodes(watch, loops) -> dict:
    """Each service's CPU per FRI cycle inside the episodes alone (us): its share of a CPU
    between the robot's own first and last cycle of each episode (its loop's
    ``wall_start_ns``/``wall_end_ns``, CLOCK_MONOTONIC as the samples are) times that
    span per cycle, averaged over the episodes by their cycles.  What a cycle's messages
    cost a service, without its start-up, the learning or the recordings' closing."""
    spent: dict = {}
    cycles = 0
    for lp in loops:
        t0, t1, n = lp.get("wall_start_ns"), lp.get("wall_end_ns"), lp["cycles"]
        share = watch.usage(t0, t1) if t0 and t1 and n else {}
        if not share:
            continue  # shorter than two samples (a settle)
        cycles += n
        for name, pct in share.items():
            if name != "seconds":
                spent[name] = spent.get(name, 0.0) + pct / 100 * (t1 - t0) / 1e3
    return {name: us / cycles for name, us in spent.items()} if cycles else {}


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
        cpu = {k: v for k, v in sorted(r["cpu"].items()) if k != "seconds"}
        print("CPU over the run (% of one CPU): " + ", ".join(f"{k} {v:.0f}" for k, v in cpu.items()))
        # each FRI cycle is one message of each 1 kHz topic: a service's CPU per cycle is
        # what each of them costs it (an upper bound: the span includes start-up and learning)
        print("CPU per FRI cycle over the run (us): " + ", ".join(
            f"{k} {v / 100 * r['cpu']['seconds'] / max(cycles_all, 1) * 1e6:.0f}" for k, v in cpu.items()))
    if r["cpu"] and not r.get("episode_cpu"):
        print("CPU per FRI cycle within the episodes: not measured (no episode of 2 s wall or more)")
    if r.get("episode_cpu"):
        inside = sorted(r["episode_cpu"].items(), key=lambda kv: -kv[1])
        print("CPU per FRI cycle within the episodes (us): " + ", ".join(f"{k} {v:.0f}" for k, v in inside)
              + f"; the run's processes {sum(v for k, v in inside if k != 'other'):.0f}")
    return dict(sim=total_sim, episode_wall=total_wall, rtf=total_sim / total_wall, per_cycle_us=per_cycle,
                own_us=sum(v for k, v in mean.items() if k != "wait"), wait_us=mean.get("wait", 0.0),
                wall=r["wall"], learn=report["learning"].get("seconds"),
                phases=report["summary"]["phases_chosen"], successes=report["summary"]["successes"],
                reproductions=report["summary"]["reproductions"],
                accuracy=report["summary"]["online_phase_accuracy"])


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default=str(ROOT / "scenarios" / "valley.yaml"))
    parser.add_argument("--floor-cycles", type=int, default=5000, help="cycles of the bare loop timed, 3 times")
    parser.add_argument("--transports", default="zenoh,inproc", help="comma-separated, run in this order")
    parser.add_argument("--out", help="folder for the runs (default: a temporary one)")
    args = parser.parse_args()
    transports = [t.strip() for t in args.transports.split(",") if t.strip()]
    base = Path(args.out or tempfile.mkdtemp(prefix="lockstep_rtf-"))
    from sim_step import physical_floor_us
    from services.transport.carriers import DEFAULT_ENGINE, ENGINES

    for t in transports:
        transport, _, engine = t.partition(":")
        if transport not in ("zenoh", "inproc") or (engine and (transport != "inproc" or engine not in ENGINES)):
            parser.error(f"--transports: {t!r} is not zenoh, inproc or inproc:ENGINE ({', '.join(ENGINES)})")

    # before the runs, the best of three: after a run over Zenoh its services' exit and a
    # busy vCPU once made the floor read 46 us instead of 12
    floor = min(physical_floor_us(args.floor_cycles) for _ in range(3))
    runs = {t: one(t, args.scenario, base / t.replace(":", "-")) for t in transports}
    for t, r in runs.items():
        if r["report"]["error"]:
            print(f"{t}: run failed: {r['report']['error']}")
            return 1
    rows = {t: episodes_table(t, r) for t, r in runs.items()}
    print(f"\n{'transport':<18} {'sim s':>7} {'episodes s':>11} {'RTF':>6} {'us/cycle':>9} {'own':>6} {'wait':>6} "
          f"{'job s':>7} {'learn s':>8}  phases  goal      accuracy")
    for t, row in rows.items():
        learn = "-" if row["learn"] is None else f"{row['learn']:.1f}"
        acc = "-" if row["accuracy"] is None else f"{row['accuracy']:.4f}"
        print(f"{t:<18} {row['sim']:7.1f} {row['episode_wall']:11.1f} {row['rtf']:6.2f} {row['per_cycle_us']:9.0f} "
              f"{row['own_us']:6.0f} {row['wait_us']:6.0f} {row['wall']:7.1f} {learn:>8}  {row['phases']!s:>6}  "
              f"{row['successes']}/{row['reproductions']:<6}  {acc}")
    if len(rows) > 1:
        from services.recordings.reader import recorded_content

        first, *others = rows
        reference = recorded_content(runs[first]["out"])
        for t in others:
            same = recorded_content(runs[t]["out"]) == reference
            print(f"{t} vs {first}: {rows[t]['rtf'] / rows[first]['rtf']:.2f}x the real-time factor over the "
                  f"episodes, the whole job {rows[first]['wall'] / rows[t]['wall']:.2f}x faster; recordings "
                  f"{'the same' if same else 'DIFFERENT'} (payloads without sent_ns)")
    print(f"\nthe floor, the bare loop of the same physics (MuJoCo's step and the KRC's law, arm on a plate): "
          f"{floor:.1f} us per cycle")
    for t, row in rows.items():
        print(f"{t:<18} cycle {row['per_cycle_us']:7.0f} us = {row['per_cycle_us'] / floor:5.1f}x the floor")
    in_process = [t for t in rows if t in ("inproc", f"inproc:{DEFAULT_ENGINE}")] or \
        [t for t in rows if t.startswith("inproc")]
    if in_process:
        name = in_process[0]
        i = rows[name]
        print(f"targets ({name}): in one process >= 15x real time over the episodes ({i['rtf']:.2f}x), the whole "
              f"job <= 45 s ({i['wall']:.1f} s), the cycle <= 5x the floor ({i['per_cycle_us'] / floor:.1f}x)"
              + (f"; over Zenoh >= 1x real time ({rows['zenoh']['rtf']:.2f}x)" if "zenoh" in rows else ""))
        stated = stated_ratio()
        ratio = i["per_cycle_us"] / floor
        if runs[name]["report"]["scenario"] != "valley":
            print("guard: held for the valley only (the stated ratio is the valley's)")
        elif failure := guard_failure(ratio, stated):
            print(failure, file=sys.stderr)
            return 3
        else:
            print(f"guard: {ratio:.1f}x the floor, within {GUARD_MARGIN} x the {stated}x "
                  f"{BENCHMARKS.relative_to(ROOT)} states")
    return 0


if __name__ == "__main__":
    sys.exit(main())
