"""ETAR against STAR on a run's demonstrations: ``etar-bench compare RUN_DIR``.

Reads the run's recorded demonstrations with their true phases (the labeller's,
recorded beside the physics), fits both transition models with the run's
number of phases over several seeds (``etar.comparison``), and writes
``RUN_DIR/comparison.json``, ``RUN_DIR/comparison.txt`` and the thesis' fig. 26,
``RUN_DIR/figures/etar_vs_star_phases.png`` (the filter's phase over one
demonstration under each model, beside the truth).  Offline only: the
reproductions a STAR model would drive are not run here.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from etar.comparison import compare_transitions, filtered_phases, summarise
from etar.task import load_task
from services.figures import FIGURES_DIR, FiguresError, _plt, _save, in_run, read_run_report
from services.recording import load_demonstration


def _demonstrations(run_dir: Path):
    report = read_run_report(run_dir)
    report_path = run_dir / "report.json"
    model_path = (report.get("learning") or {}).get("model")
    if not model_path or not report.get("demonstrations"):
        raise FiguresError(f"{report_path}: the run has no demonstrations and learned model to compare on")
    task = load_task(in_run(run_dir, model_path))
    demos = [load_demonstration(in_run(run_dir, d["path"]), state=task.state, features=task.features)
             for d in report["demonstrations"]]
    return task, demos


def _verdict(summary: dict) -> list[str]:
    """A line per figure (which model is better, by how much against the spread between
    seeds), then whether the thesis' claim holds: ETAR's filter more accurate and not
    less smooth, STAR's one-step predictions worse near the transitions."""
    e, s = summary["ETAR"], summary["STAR"]
    lines, verdicts = [], {}
    for key, what, higher_better in (("filter_accuracy", "online filter accuracy", True),
                                     ("viterbi_accuracy", "Viterbi accuracy", True),
                                     ("filter_mean_transition_error_s", "filter transition-time error [s]", False),
                                     ("filter_spurious_switches", "filter spurious switches", False),
                                     ("error_near_transitions", "one-step error near transitions", False)):
        a, b = e[key]["mean"], s[key]["mean"]
        spread = max(e[key]["max"] - e[key]["min"], s[key]["max"] - s[key]["min"])
        if a == b:
            who = "equal"
        else:
            who = "ETAR" if (a > b) == higher_better else "STAR"
            if abs(a - b) <= spread:
                who += " (within the spread between seeds)"
        verdicts[key] = who
        lines.append(f"  {what:<36} ETAR {a:10.4g} (seeds {e[key]['min']:.4g}..{e[key]['max']:.4g})   "
                     f"STAR {b:10.4g} ({s[key]['min']:.4g}..{s[key]['max']:.4g})   better: {who}")
    parts = [verdicts["filter_accuracy"], verdicts["filter_spurious_switches"], verdicts["error_near_transitions"]]
    if all(v == "ETAR" for v in (parts[0], parts[2])) and parts[1] in ("ETAR", "equal"):
        held = "HOLDS"
    elif all(v.startswith("ETAR") or v == "equal" for v in parts):
        held = "holds in direction only: the differences are within the spread between seeds"
    else:
        held = "does NOT hold"
    lines.append(f"the thesis' claim (ETAR's transitions smoother and more accurate, STAR's predictions worse at "
                 f"transitions) {held} here: more accurate: {parts[0]}; smoother (fewer spurious switches): "
                 f"{parts[1]}; worse at transitions: {'STAR' if parts[2].startswith('ETAR') else parts[2]}")
    return lines


def compare_run(run_dir, seeds=(0, 1, 2), progress=None) -> dict:
    run_dir = Path(run_dir)
    task, demos = _demonstrations(run_dir)
    pairs = [(d["states"], d["forces"]) for d in demos]
    truths = [d["phases"] for d in demos]
    dt = float(demos[0]["dt"])
    K = task.model.n_phases
    evals = compare_transitions(pairs, truths, K, dt, seeds=seeds, n_restarts=task.model.n_restarts,
                                progress=progress)
    summary = summarise(evals)
    result = {"run": str(run_dir), "phases": K, "demonstrations": len(demos), "seeds": list(seeds),
              "summary": summary, "evaluations": [e.to_dict() for e in evals]}
    (run_dir / "comparison.json").write_text(json.dumps(result, indent=1) + "\n")
    text = [f"ETAR against STAR on {len(demos)} demonstrations of {run_dir}, {K} phases, seeds "
            f"{', '.join(map(str, seeds))} (etar-bench compare)", *_verdict(summary)]
    (run_dir / "comparison.txt").write_text("\n".join(text) + "\n")
    _figure(run_dir, demos[0], truths[0], K, evals[:2])
    return result


def _figure(run_dir: Path, demo: dict, truth, K: int, evals) -> Path:
    """Demonstration 0 under the first seed's two models, their phases matched to the truth."""
    plt = _plt()
    t = demo["t"][1:] - demo["t"][0]
    fig, axes = plt.subplots(3, 1, figsize=(10, 6), sharex=True)
    axes[0].step(t, truth, where="post", color="black")
    axes[0].set_ylabel("true phase")
    for ax, e in zip(axes[1:], evals):
        name = "ETAR (force)" if e.transitions == "effect" else "STAR (position)"
        mapping = e.filtered.mapping
        ax.step(t, [mapping.get(int(p), -1) for p in e.filtered_labels[0]], where="post")
        ax.set_ylabel(f"{name}\nfiltered phase")
    for ax in axes:
        ax.set_yticks(range(K))
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"Estimated phase sequence with effect-of-action (ETAR) and state-based (STAR) transitions, "
                 f"demonstration 0, seed {evals[0].seed}\n(thesis fig. 26; phases matched to the truth)")
    out = run_dir / FIGURES_DIR
    out.mkdir(exist_ok=True)
    return _save(fig, out / "etar_vs_star_phases.png")
