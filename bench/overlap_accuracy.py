"""A run's online phase accuracy with each learned phase scored as the true phase it
overlaps most on the demonstrations (many-to-one), beside the report's one-to-one.

The report matches learned to true phases one to one (Hungarian), so a model with more
phases than the task has true ones (the two-sided valley learned with 4: a phase per
plate) has phases that count wrong wherever they are.  Scored many to one, a learned
phase counts right wherever the true phase it mostly stands for holds.

    python bench/overlap_accuracy.py RUN_DIR

RUN_DIR: a finished run (``etar-bench run``) with its demonstrations and reproductions
recorded and ``model.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from services.runtime.messages import ESTIMATOR_PHASE, ROBOT_CONTACT  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a finished run's folder (report.json, model.json, recordings/)")
    args = ap.parse_args(argv)
    for name in ("report.json", "model.json"):
        if not (args.run / name).is_file():
            ap.error(f"{args.run / name}: missing (is {args.run} a finished run's folder?)")

    try:
        return study(args.run, ap)
    except (OSError, ValueError, KeyError, TypeError) as e:  # a report, model or recording that does not read
        ap.exit(2, f"{ap.prog}: error: {type(e).__name__}: {e}\n")


def study(run: Path, ap: argparse.ArgumentParser) -> int:
    from etar.task import load_task
    from services.recordings.arrays import topic_arrays
    from services.recordings.demonstrations import load_demonstration

    report = json.loads((run / "report.json").read_text())
    task = load_task(run / "model.json")
    if not report.get("demonstrations"):
        ap.error(f"{run}: no recorded demonstrations to match the phases on")
    demos = [load_demonstration(run / d["path"], state=task.state, features=task.features,
                                state_resolution=task.state_resolution) for d in report["demonstrations"]]
    n_true = int(max(np.max(d["phases"]) for d in demos)) + 1
    overlap = np.zeros((task.n_phases, n_true), dtype=np.int64)
    for d in demos:
        np.add.at(overlap, (task.model.viterbi(d["states"], d["forces"]), np.asarray(d["phases"])), 1)
    many_to_one = {k: int(np.argmax(overlap[k])) for k in range(task.n_phases)}
    print(f"{run}: {task.n_phases} learned phases; samples (learned x true) on the demonstrations "
          f"{overlap.tolist()}; many to one {many_to_one}")
    by_side: dict[str, list] = {}
    for rp in report["reproductions"]:
        path = run / rp["path"]
        estimates, contact = topic_arrays(path, ESTIMATOR_PHASE.topic), topic_arrays(path, ROBOT_CONTACT.topic)
        truth = dict(zip(contact["seq"].tolist(), contact["true_phase"].tolist()))
        scored = [many_to_one[int(p)] == truth[s] for s, p in zip(estimates["seq"].tolist(),
                                                                   estimates["phase"].tolist()) if s in truth]
        accuracy = float(np.mean(scored)) if scored else float("nan")
        by_side.setdefault(rp.get("side") or "-", []).append(accuracy)
        one = (rp.get("phases") or {}).get("accuracy")
        print(f"  reproduction {rp['index']:2d} {rp.get('side') or '-':<5} {rp['reason']:<16} one to one "
              f"{one if one is None else round(one, 3)}  many to one {accuracy:.3f}")
    for side, acc in by_side.items():
        print(f"{side}: many to one, mean {np.mean(acc):.3f} (min {min(acc):.3f}, max {max(acc):.3f}) "
              f"over {len(acc)} reproductions")
    return 0


if __name__ == "__main__":
    sys.exit(main())
