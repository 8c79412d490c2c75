"""When the online estimate changes phase against when the true phase does, per transition.

    python bench/transition_timing.py out/valley                  # a run's reproductions
    python bench/transition_timing.py sweeps/v/runs/*             # several runs, pooled

The report's transition error is one number per reproduction; this splits it by which
transition it is (free -> plate, plate -> groove, ...): for every true change of phase in a
reproduction, the first estimate (its phase mapped to the truth as the report maps it, by
the robot cycle it used) that reaches the new phase, its delay in seconds (negative: early),
and how often the estimate left the new phase again within the next second.  Reads the
run's report.json and its recordings (``--record full``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from services.runtime.messages import ESTIMATOR_PHASE, ROBOT_CONTACT


def transitions(run: Path) -> list[dict]:
    from services.recordings.arrays import recording_arrays

    report = json.loads((run / "report.json").read_text())
    out = []
    for rp in report["reproductions"]:
        path = run / rp["path"]
        if not rp.get("phases") or not path.exists():
            continue
        mapping = {int(k): v for k, v in rp["phases"]["mapping"].items()}
        a = recording_arrays(path, skip_bad=True, topics=(ROBOT_CONTACT.channel, ESTIMATOR_PHASE.channel))
        c, e = a[ROBOT_CONTACT.channel], a[ESTIMATOR_PHASE.channel]
        true_seq, true_phase = c["seq"], c["true_phase"]
        est_seq = e["input_seq"]
        est = np.array([mapping.get(int(p), -1) for p in e["phase"]])
        for k in np.flatnonzero(np.diff(true_phase) != 0) + 1:
            old, new, at = int(true_phase[k - 1]), int(true_phase[k]), int(true_seq[k])
            reached = np.flatnonzero((est == new) & (est_seq >= at - 2000))
            first = int(est_seq[reached[0]]) if len(reached) else None
            after = (est_seq > at) & (est_seq <= at + 1000)
            out.append({"run": run.name, "index": rp["index"], "model": rp.get("model"), "from": old, "to": new,
                        "delay_s": None if first is None else (first - at) / 1000.0,
                        "left_again": int(np.sum(np.diff((est[after] == new).astype(int)) == -1))})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="runs' folders (report.json and recordings/)")
    args = ap.parse_args(argv)
    rows = []
    for run in args.runs:
        if not (run / "report.json").exists():
            print(f"transition_timing: {run}: no report.json (a run's folder recorded in full?)", file=sys.stderr)
            return 2
        rows += transitions(run)
    if not rows:
        print("transition_timing: no reproduction with recordings and scored phases", file=sys.stderr)
        return 2
    print(f"{'transition':<12} {'n':>4} {'median delay s':>15} {'p10 .. p90 s':>16} {'never':>6} {'left again':>11}")
    for pair in sorted({(r["from"], r["to"]) for r in rows}):
        mine = [r for r in rows if (r["from"], r["to"]) == pair]
        d = np.array([r["delay_s"] for r in mine if r["delay_s"] is not None])
        spread = f"{np.quantile(d, 0.1):+.3f} .. {np.quantile(d, 0.9):+.3f}" if len(d) else "-"
        median = f"{np.median(d):+.3f}" if len(d) else "-"
        print(f"{pair[0]} -> {pair[1]:<7} {len(mine):>4} {median:>15} {spread:>16} {len(mine) - len(d):>6} "
              f"{sum(r['left_again'] for r in mine):>11}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
