"""ETAR against STAR on a run's demonstrations, and Table C1's check: ``etar-bench compare RUN_DIR``.

Reads the run's recorded demonstrations with their true phases (the labeller's,
recorded beside the physics), fits both transition models with the run's
number of phases over several seeds (``etar.comparison``), and writes
``RUN_DIR/comparison.json``, ``RUN_DIR/comparison.txt`` and the thesis' fig. 26,
``RUN_DIR/figures/etar_vs_star_phases.png`` (the filter's phase over one
demonstration under each model, beside the truth).  Table C1's check: two of
the demonstrations (``--pair``) learned separately, their parameters compared
after matching the phases, beside the distance two seeds' fits of one
demonstration land apart.

Offline only; the reproductions each model drives are a scenario's
(``scenarios/star_vs_etar.yaml``: the learn and reproduce stages take
``transitions: [effect, state]``), whose report and sweep use ``verdict`` here.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from etar.comparison import PARAMETERS, compare_transitions, separate_fits, spread, summarise
from etar.task import load_task
from services.results.figures import COMPARISON_FIGURE, FIGURES_DIR, FiguresError, canvas, in_run, read_run_report
from services.recordings.demonstrations import load_demonstration
from services.runtime.files import write_file


def _demonstrations(run_dir: Path):
    report = read_run_report(run_dir)
    report_path = run_dir / "report.json"
    model_path = (report.get("learning") or {}).get("model")
    if not model_path or not report.get("demonstrations"):
        raise FiguresError(f"{report_path}: the run has no demonstrations and learned model to compare on")
    task = load_task(in_run(run_dir, model_path))
    demos = [load_demonstration(in_run(run_dir, d["path"]), state=task.state, features=task.features,
                               state_resolution=task.state_resolution)
             for d in report["demonstrations"]]
    return task, demos


# (key, what, higher is better); the offline ones from etar.comparison.summarise, the
# online ones from the reproductions each model drove (services.results.report.by_model)
OFFLINE = (("filter_accuracy", "online filter accuracy (offline, demos)", True),
           ("viterbi_accuracy", "Viterbi accuracy (offline, demos)", True),
           ("filter_mean_transition_error_s", "filter transition-time error [s]", False),
           ("filter_spurious_switches", "filter spurious switches", False),
           ("error_near_transitions", "one-step error near transitions", False))
ONLINE = (("success_rate", "reproductions reaching the goal", True),
          ("online_phase_accuracy", "phase accuracy in reproductions", True),
          ("mean_transition_error_s", "transition-time error in repro. [s]", False),
          ("mean_peak_contact_force_n", "peak contact force in repro. [N]", False))


def verdict(summary: dict) -> list[str]:
    """A line per figure (which model is better, by how much against the spread between
    seeds), then whether the thesis' claim holds: ETAR's phase estimate more accurate and
    not less smooth, STAR's one-step predictions worse near the transitions.

    ``summary``: {"ETAR": {key: {mean, min, max, n}}, "STAR": {...}} over any of the keys
    of OFFLINE and ONLINE.  With one seed there is no spread to weigh a difference
    against, and the verdict says so."""
    e, s = summary.get("ETAR", {}), summary.get("STAR", {})
    lines, better = [], {}
    for key, what, higher_better in OFFLINE + ONLINE:
        if e.get(key) is None or s.get(key) is None:
            continue
        a, b = e[key]["mean"], s[key]["mean"]
        seeds = min(e[key].get("n", 1), s[key].get("n", 1))
        if a == b:
            who = "equal"
        else:
            who = "ETAR" if (a > b) == higher_better else "STAR"
            if seeds < 2:
                who += " (one seed: no spread to weigh it against)"
            elif not beyond_spread(a, b, e[key]["max"] - e[key]["min"], s[key]["max"] - s[key]["min"]):
                who += " (within the spread between seeds)"
        better[key] = who
        lines.append(f"  {what:<40} ETAR {a:10.4g} ({e[key]['min']:.4g}..{e[key]['max']:.4g})   "
                     f"STAR {b:10.4g} ({s[key]['min']:.4g}..{s[key]['max']:.4g})   better: {who}")
    accurate = [better[k] for k in ("filter_accuracy", "online_phase_accuracy") if k in better]
    smooth = better.get("filter_spurious_switches")
    near = better.get("error_near_transitions")
    if not accurate or smooth is None or near is None:
        return lines
    parts = accurate + [near, smooth]
    in_direction = all(v.startswith("ETAR") or v == "equal" for v in parts)
    if all(min(e[k].get("n", 1), s[k].get("n", 1)) < 2 for k in better):
        held = f"cannot be judged from one seed (in direction it {'holds' if in_direction else 'does not hold'})"
    elif "STAR" in parts:
        held = "does NOT hold"
    elif all(v == "ETAR" for v in accurate + [near]) and smooth in ("ETAR", "equal"):
        held = "HOLDS"
    elif in_direction:
        held = "holds in direction only: the differences are not larger than the spread between seeds"
    else:
        held = "is not decided here: the differences either way are not larger than the spread between seeds"
    worse = ("STAR" + near[4:]) if near.startswith("ETAR") else (("ETAR" + near[4:]) if near.startswith("STAR")
                                                                else near)
    lines.append(f"the thesis' claim (ETAR's transitions smoother and more accurate, STAR's predictions worse at "
                 f"transitions) {held}. More accurate: {'; '.join(accurate)}. Smoother (fewer spurious "
                 f"switches): {smooth}. Predictions worse at transitions: {worse}")
    return lines


def paired(rows_by_seed: dict) -> list[str]:
    """Per figure, in how many data seeds each model was the better: a paired count, which a
    spread over seeds that moves both models together hides.  ``rows_by_seed``: {seed:
    {"ETAR": {key: value}, "STAR": {key: value}}}."""
    lines = []
    for key, what, higher_better in OFFLINE + ONLINE:
        pairs = [(m["ETAR"].get(key), m["STAR"].get(key)) for m in rows_by_seed.values()
                 if "ETAR" in m and "STAR" in m]
        pairs = [(a, b) for a, b in pairs if a is not None and b is not None and np.isfinite(a) and np.isfinite(b)]
        if not pairs:
            continue
        etar, star, equal = paired_counts(pairs, higher_better)
        lines.append(f"  {what:<40} ETAR better in {etar} of {len(pairs)} seeds, STAR in {star}, equal in {equal}")
    return lines


def paired_counts(pairs, higher_better: bool) -> tuple[int, int, int]:
    """Of (ETAR, STAR) pairs of one figure (a pair per data seed): in how many ETAR was
    the better, in how many STAR, in how many they were equal."""
    pairs = list(pairs)
    etar = sum((a > b) == higher_better and a != b for a, b in pairs)
    star = sum((a < b) == higher_better and a != b for a, b in pairs)
    return etar, star, len(pairs) - etar - star


def beyond_spread(a: float, b: float, range_a: float, range_b: float) -> bool:
    """Two models' means of a figure differ by more than either model's range over the
    data seeds: the one difference this project calls a result."""
    return a != b and abs(a - b) > max(range_a, range_b)


def run_summary(reports: list[dict]) -> dict:
    """Per model, each figure's mean and spread over runs (one run per data seed)."""
    out = {}
    for name in ("ETAR", "STAR"):
        offline = [o for r in reports for o in r["learning"].get("offline", []) if o["model"] == name]
        online = [r["summary"].get("by_model", {}).get(name) for r in reports]
        online = [o for o in online if o]
        if not offline and not online:
            continue
        figures = {
            "filter_accuracy": spread(o["filtered"]["accuracy"] for o in offline),
            "viterbi_accuracy": spread(o["viterbi"]["accuracy"] for o in offline),
            "filter_mean_transition_error_s": spread(o["filtered"]["mean_transition_error_s"] for o in offline),
            "filter_spurious_switches": spread(o["filtered"]["spurious_switches"] for o in offline),
            "error_near_transitions": spread(o["error_near_transitions"] for o in offline),
        }
        figures.update({key: spread(o[key] for o in online) for key, _, _ in ONLINE})
        out[name] = {k: v for k, v in figures.items() if v is not None}
    return out


def comparison_text(report: dict) -> list[str]:
    """The ETAR-against-STAR lines of one run's report (its learn stage fitted both)."""
    summary = run_summary([report])
    lines = ["ETAR against STAR (thesis 6.3), one data seed: offline on the demonstrations' true phases, "
             "online on the same reproduction starts"]
    for name, m in report["summary"].get("by_model", {}).items():
        lines.append(f"  {name}: {m['successes']} of {m['reproductions']} reached the goal")
    return lines + verdict(summary)


def table_c1(demos: list, pair: tuple[int, int], K: int, seeds, n_restarts: int, progress=None) -> dict:
    """Thesis Table C1's check on two of the run's demonstrations (see etar.comparison.separate_fits)."""
    i, j = pair
    a, b = demos[i], demos[j]
    result = separate_fits((a["states"], a["forces"]), (b["states"], b["forces"]), K, seeds=seeds,
                           truths=(a["phases"], b["phases"]), n_restarts=n_restarts, progress=progress)
    models = result.pop("models")
    first = result["between_demonstrations"][0]
    perm = first["permutation"]
    ma, mb = models[f"a_seed{seeds[0]}"], models[f"b_seed{seeds[0]}"]
    # the seed's two fits side by side, b's phases in a's order (as the thesis' table)
    result["parameters"] = {"seed": int(seeds[0]), "demonstrations": [i, j],
                            "a": {k: np.asarray(getattr(ma, k)).tolist() for k in PARAMETERS},
                            "b_matched": {k: np.asarray(getattr(mb, k))[perm].tolist() for k in ("A", "B", "Sigma")},
                            "b_permutation": perm}
    result["demonstrations"] = [i, j]
    return result


def table_c1_text(c1: dict) -> list[str]:
    i, j = c1["demonstrations"]
    lines = [f"Table C1 check: demonstrations {i} and {j} learned separately ({c1['phases']} phases, seeds "
             f"{', '.join(map(str, c1['seeds']))}), phases matched by their dynamics (Hungarian); relative "
             f"distance ||x - y|| / mean(||x||, ||y||) of each parameter, W without its softmax gauge",
             f"  {'parameter':<10} {'between the demonstrations':>30} {'between seeds, one demonstration':>36}"]
    for k in PARAMETERS:
        bd, bs = c1["summary"][k]["between_demonstrations"], c1["summary"][k]["between_seeds"]
        fmt = lambda st: "-" if st is None else f"{st['mean']:.3g} ({st['min']:.3g}..{st['max']:.3g})"  # noqa: E731
        lines.append(f"  {k:<10} {fmt(bd):>30} {fmt(bs):>36}")
    agree = [r.get("matching_agrees_with_truth") for r in c1["between_demonstrations"]]
    perms = [r["permutation"] for r in c1["between_demonstrations"]]
    lines.append(f"  phase matching (b's phase for each of a's) by seed: {perms}; the same as the true phases' "
                 f"matching: {agree}")
    return lines


def compare_run(run_dir, seeds=(0, 1, 2), progress=None, pair=(0, 1)) -> dict:
    run_dir = Path(run_dir)
    task, demos = _demonstrations(run_dir)
    if len(demos) < 2 or max(pair) >= len(demos) or pair[0] == pair[1] or min(pair) < 0:
        raise FiguresError(f"{run_dir / 'report.json'}: Table C1 needs two different demonstrations of the run's "
                           f"{len(demos)}; --pair {pair[0]},{pair[1]} does not name them")
    pairs = [(d["states"], d["forces"]) for d in demos]
    truths = [d["phases"] for d in demos]
    dt = float(demos[0]["dt"])
    K = task.model.n_phases
    evals = compare_transitions(pairs, truths, K, dt, seeds=seeds, n_restarts=task.model.n_restarts,
                                progress=progress)
    summary = summarise(evals)
    c1 = table_c1(demos, pair, K, seeds, task.model.n_restarts, progress)
    result = {"run": str(run_dir), "phases": K, "demonstrations": len(demos), "seeds": list(seeds),
              "summary": summary, "evaluations": [e.to_dict() for e in evals], "table_c1": c1}
    write_file(run_dir / "comparison.json", json.dumps(result, indent=1) + "\n")
    text = [f"ETAR against STAR on {len(demos)} demonstrations of {run_dir}, {K} phases, EM seeds "
            f"{', '.join(map(str, seeds))} (etar-bench compare)", *verdict(summary), "", *table_c1_text(c1)]
    write_file(run_dir / "comparison.txt", "\n".join(text) + "\n")
    _figure(run_dir, demos[0], truths[0], K, evals[:2])
    return result


def _figure(run_dir: Path, demo: dict, truth, K: int, evals) -> Path:
    """Demonstration 0 under the first seed's two models, their phases matched to the truth."""
    plt = canvas.pyplot()
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
    return canvas.save(fig, out / COMPARISON_FIGURE)


def comparison_over_seeds(rows: list[dict]) -> list[str] | None:
    """ETAR against STAR over a sweep's runs (one per data seed, its rows as
    ``services.run.sweep_table.by_model_rows`` gives them): ``verdict`` on each figure's mean and
    spread over the runs, for each swept value on its own (a sweep over the sensor's noise
    compares the models at each noise level, never across them)."""
    rows = [r for r in rows if r.get("param model") in ("ETAR", "STAR") and not r.get("error")]
    if not rows:
        return None
    swept = [k for k in rows[0] if k.startswith("param ") and k != "param model"]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(r.get(k) for k in swept), []).append(r)
    if len(groups) == 1:
        return _over_seeds(rows)
    lines = []
    for values, group in groups.items():
        at = ", ".join(f"{k.removeprefix('param ')}={v}" for k, v in zip(swept, values))
        lines += [f"at {at}:", *_over_seeds(group), ""]
    return lines[:-1]


def _over_seeds(rows: list[dict]) -> list[str]:
    summary = {name: {k: st for k, _, _ in OFFLINE + ONLINE
                      if (st := spread(r.get(k) for r in rows if r["param model"] == name)) is not None}
               for name in ("ETAR", "STAR")}
    seeds = sorted({r["seed"] for r in rows})
    by_seed = {}
    for r in rows:
        by_seed.setdefault(r["seed"], {})[r["param model"]] = r
    return [f"ETAR against STAR over {len(seeds)} data seed(s) ({', '.join(map(str, seeds))}): each figure's "
            f"mean over the runs (min..max)", *verdict(summary),
            "paired by data seed (the same demonstrations and starts for both models):", *paired(by_seed)]
