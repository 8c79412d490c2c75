"""ETAR against STAR where the emissions decide less: the table and the figure of one or
more sweeps of ``scenarios/star_vs_etar.yaml`` (thesis 6.3, fig. 26).

On the valley's demonstrations the AR emissions decide the phase and the transition
model hardly matters.  Swept over the sensor's noise and over a coarser state
(``state_resolution``: ETAR's position rounded to a grid), the emissions say less per
step; this lays the two models side by side at every swept value, over the data seeds:
each figure's mean and range, and the paired count (the same demonstrations and
starts for both models) of seeds in which each was the better.

    etar-bench sweep scenarios/star_vs_etar.yaml --param cell.sensor_noise=1,16,64,256 \\
        --repeats 5 --record summary --out runs/noise
    etar-bench sweep scenarios/star_vs_etar.yaml --param state_resolution=0,0.0001,0.0003 \\
        --param learn.phases=3 --repeats 5 --record summary --out runs/coarse
    etar-bench sweep scenarios/star_vs_etar.yaml --param state_resolution=0.0003 \\
        --param learn.phases=3 --repeats 10 --record summary --out runs/coarse10
    python bench/star_vs_etar_sweep.py runs/noise runs/coarse runs/coarse10 --out runs/star-vs-etar

A parameter given one value (``learn.phases=3``) holds for its sweep and is said above
its table.  Sweeps of the same parameter with the same fixed ones are laid out as one
(more values, or more seeds at a value).  A sweep's first value of another sweep's
parameter can stand in for this sweep's missing one (``--baseline PARAM=VALUE``: the
noise sweep's noise 1 is a resolution sweep's 0, if both choose their phases alike).
Writes ``OUT/star_vs_etar.md`` (the table) and ``OUT/star_vs_etar.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from services.results.compare import OFFLINE, ONLINE, beyond_spread, paired_counts

# which way is better, and the counting rules, are services.results.compare's; here only
# how a figure is named in the table and labelled on the plot: (key in a sweep's table,
# what, the figure's label)
HIGHER_BETTER = {key: higher for key, _, higher in OFFLINE + ONLINE}
FIGURES = (("filter_accuracy", "filter accuracy, offline on the demonstrations", "filter accuracy\n(offline)"),
           ("filter_mean_transition_error_s", "filter transition-time error, offline [s]",
            "transition error [s]\n(offline)"),
           ("filter_spurious_switches", "filter spurious switches, offline", "spurious switches\n(offline)"),
           ("error_near_transitions", "one-step error near transitions, offline [m^2]",
            "one-step error near\ntransitions [m^2] (offline)"),
           ("online_phase_accuracy", "phase accuracy in the reproductions", "phase accuracy\n(reproductions)"),
           ("mean_transition_error_s", "transition-time error in the reproductions [s]",
            "transition error [s]\n(reproductions)"),
           ("success_rate", "reproductions reaching the goal", "reaching the goal"))
MODELS = ("ETAR", "STAR")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sweeps", type=Path, nargs="+", help="sweep folders (sweep.json, table.json) of "
                    "scenarios/star_vs_etar.yaml, each over one parameter")
    ap.add_argument("--baseline", action="append", default=[], metavar="PARAM=VALUE",
                    help="PARAM at VALUE is what the other sweeps ran with: their runs at their first value "
                    "stand in for it (e.g. state_resolution=0)")
    ap.add_argument("--out", type=Path, required=True, help="folder for star_vs_etar.md and star_vs_etar.png")
    args = ap.parse_args(argv)
    baselines = {}
    for item in args.baseline:
        name, sep, value = item.partition("=")
        try:
            baselines[name] = float(value)
        except ValueError:
            ap.error(f"--baseline {item}: expected PARAM=NUMBER")
        if not sep or not name:
            ap.error(f"--baseline {item}: expected PARAM=NUMBER")
    try:
        sweeps = _merged([_read(path) for path in args.sweeps])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        ap.exit(2, f"{ap.prog}: error: {exc}\n")
    if not args.out.parent.is_dir():
        ap.error(f"--out {args.out}: its parent folder does not exist")
    for name, value in baselines.items():
        donors = [s for s in sweeps if s["parameter"] != name]
        for s in sweeps:
            if s["parameter"] == name and donors:
                donor = donors[0]
                first = donor["values"][0]
                s["rows"] += [dict(r, **{f"param {name}": value}) for r in donor["rows"]
                              if r.get(f"param {donor['parameter']}") == first]
                s["values"] = sorted({value, *s["values"]})
                s["baseline_from"] = f"{donor['path']} at {donor['parameter']}={first}"
    args.out.mkdir(exist_ok=True)
    table = args.out / "star_vs_etar.md"
    table.write_text("\n".join(_table(sweeps)) + "\n")
    figure = _figure(sweeps, args.out / "star_vs_etar.png")
    print(table.read_text(), end="")
    print(f"wrote {table} and {figure}")
    return 0


def _read(path: Path) -> dict:
    summary = json.loads((path / "sweep.json").read_text())
    rows = json.loads((path / "table.json").read_text())
    # a parameter given one value (--param learn.phases=3) holds for the whole sweep: said, not
    # swept; where every one has a single value, the first given is the one laid out
    params = {p: v for p, v in summary["parameters"].items() if p != "model"}
    swept = [p for p, v in params.items() if len(v) > 1] or list(params)[:1]
    if len(swept) != 1:
        raise ValueError(f"{path / 'sweep.json'}: parameters: expected one swept over several values besides the "
                         f"model, got {swept or 'none'}")
    fixed = {p: v[0] for p, v in params.items() if p != swept[0]}
    if not any(r.get("param model") in MODELS for r in rows):
        raise ValueError(f"{path / 'table.json'}: no ETAR and STAR rows (a sweep of scenarios/star_vs_etar.yaml?)")
    failed = sorted({r["run"] for r in rows if r.get("error")})
    return dict(path=str(path), parameter=swept[0], values=list(summary["parameters"][swept[0]]),
                rows=[r for r in rows if not r.get("error")], failed=failed, baseline_from=None, fixed=fixed)


def _merged(sweeps: list[dict]) -> list[dict]:
    """Sweeps of the same parameter with the same fixed ones laid out as one (more values,
    or more seeds at a value); a (value, seed, model) run twice is taken once, from the
    first sweep given (the same seed gives the same run)."""
    out: dict = {}
    for s in sweeps:
        key = (s["parameter"], tuple(sorted(s["fixed"].items())))
        if key not in out:
            out[key] = dict(s, rows=list(s["rows"]), values=list(s["values"]), failed=list(s["failed"]))
            continue
        m = out[key]
        col = f"param {s['parameter']}"
        seen = {(r.get(col), r.get("seed"), r.get("param model")) for r in m["rows"]}
        m["rows"] += [r for r in s["rows"] if (r.get(col), r.get("seed"), r.get("param model")) not in seen]
        m["values"] = sorted({*m["values"], *s["values"]})
        m["failed"] += s["failed"]
        m["path"] += f", {s['path']}"
    return list(out.values())


def _by_value(sweep: dict, value, key: str) -> dict:
    """{model: {seed: figure}} at one value of the sweep's parameter."""
    col = f"param {sweep['parameter']}"
    out: dict = {m: {} for m in MODELS}
    for r in sweep["rows"]:
        v = r.get(key)
        if r.get(col) == value and r.get("param model") in MODELS and v is not None and math.isfinite(v):
            out[r["param model"]][r["seed"]] = float(v)
    return out


def _fmt(x: float) -> str:
    return f"{x:.4g}"


def _table(sweeps: list[dict]) -> list[str]:
    lines = ["# ETAR against STAR where the emissions decide less",
             "",
             "Each figure's mean over the data seeds (min..max); `paired`: in how many seeds each model was",
             "the better (same demonstrations, same starts); `beyond spread`: the difference of the means",
             "is larger than either model's range over the seeds.", ""]
    for s in sweeps:
        lines.append(f"## {s['parameter']} ({s['path']})")
        if s["fixed"]:
            lines.append("with " + ", ".join(f"{k}={v}" for k, v in s["fixed"].items()))
        if s["baseline_from"]:
            lines.append(f"(the baseline value: the runs of {s['baseline_from']})")
        if s["failed"]:
            lines.append(f"runs that failed to run: {', '.join(s['failed'])}")
        lines += ["", f"| {s['parameter']} | figure | seeds | ETAR | STAR | paired: ETAR / STAR / equal | "
                      "beyond spread |", "|---|---|---|---|---|---|---|"]
        for value in s["values"]:
            for key, what, _ in FIGURES:
                higher = HIGHER_BETTER[key]
                m = _by_value(s, value, key)
                seeds = sorted(m["ETAR"].keys() & m["STAR"].keys())
                if not seeds:
                    continue
                e = np.array([m["ETAR"][k] for k in seeds])
                t = np.array([m["STAR"][k] for k in seeds])
                etar, star, equal = paired_counts(zip(e, t), higher)
                beyond = beyond_spread(e.mean(), t.mean(), np.ptp(e), np.ptp(t))
                better = ("ETAR" if (e.mean() > t.mean()) == higher else "STAR") if beyond else "no"
                lines.append(f"| {value:g} | {what} | {len(seeds)} | {_fmt(e.mean())} ({_fmt(e.min())}..{_fmt(e.max())})"
                             f" | {_fmt(t.mean())} ({_fmt(t.min())}..{_fmt(t.max())}) | {etar} / {star} / "
                             f"{equal} | {better} |")
        lines.append("")
    return lines


def _figure(sweeps: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [f for f in FIGURES if f[0] != "success_rate"]
    fig, axes = plt.subplots(len(shown), len(sweeps), figsize=(5.2 * len(sweeps), 2.3 * len(shown)),
                             squeeze=False, sharex="col")
    for c, s in enumerate(sweeps):
        values = s["values"]
        # the baseline 0 of a resolution cannot sit on a log axis: evenly spaced values, labelled
        xs = np.arange(len(values), dtype=float)
        for r, (key, _, label) in enumerate(shown):
            ax = axes[r, c]
            positive = False
            by_value = [_by_value(s, v, key) for v in values]
            for n, model in enumerate(MODELS):
                per_value = [m[model] for m in by_value]
                mean = np.array([np.mean(list(d.values())) if d else np.nan for d in per_value])
                lo = np.array([min(d.values()) if d else np.nan for d in per_value])
                hi = np.array([max(d.values()) if d else np.nan for d in per_value])
                shift = (n - 0.5) * 0.08
                ax.fill_between(xs, lo, hi, color=f"C{n}", alpha=0.15, lw=0)
                ax.plot(xs, mean, "-o", ms=3, color=f"C{n}", label=f"{model} (mean; band: min..max over seeds)")
                for x, d in zip(xs, per_value):
                    ax.scatter([x + shift] * len(d), list(d.values()), s=9, color=f"C{n}", alpha=0.6)
                    positive |= any(v > 0 for v in d.values())
            if "error_near" in key and positive:  # a log axis needs something above 0 to show
                ax.set_yscale("log")
            ax.set_ylabel(label, fontsize=8)
            ax.grid(alpha=0.3)
            ax.set_xticks(xs, [f"{v:g}" for v in values])
        axes[-1, c].set_xlabel(s["parameter"] + (" [m]" if s["parameter"] == "state_resolution" else
                                                 " [x Mini45]" if "sensor_noise" in s["parameter"] else ""))
        axes[0, c].set_title(f"over {s['parameter']}", fontsize=9)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("ETAR (force-driven transitions)\nagainst STAR (state-driven)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


if __name__ == "__main__":
    sys.exit(main())
