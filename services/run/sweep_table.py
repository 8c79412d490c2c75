"""A sweep's products beside its runs: the table of every run's figures (``table.csv``,
``table.json``, a row per run, or per model where a run reproduced with several) and a
plot per parameter (``services.run.sweep`` writes them)."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

from services.runtime.files import write_file, write_via

METRICS = (("phases_chosen", "phases chosen"), ("success_rate", "reproductions reaching the goal (fraction)"),
           ("online_phase_accuracy", "online phase accuracy"),
           ("mean_transition_error_s", "mean transition-time error [s]"),
           ("peak_contact_force_n", "peak contact force [N]"))


def by_model_rows(rows: list[dict]) -> list[dict]:
    """A run that reproduced with several models becomes one row per model (``param
    model``), its overall figures replaced by that model's; other rows stay as they are."""
    out = []
    for row in rows:
        models = row.get("by_model")
        if not models:
            out.append(row)
            continue
        base = {k: v for k, v in row.items() if k != "by_model"}
        for name, figures in models.items():
            r = dict(base, **{"param model": name}, **figures)
            if r.get("reproductions") and figures.get("success_rate") is not None:
                r["reproductions"] = None  # the run's count is of every model's reproductions
                r["successes"] = None
            r["peak_contact_force_n"] = figures.get("mean_peak_contact_force_n", r.get("peak_contact_force_n"))
            out.append(r)
    return out


def write_table(rows: list[dict], out: Path) -> tuple[Path, Path]:
    columns = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    csv_path, json_path = out / "table.csv", out / "table.json"
    text = io.StringIO(newline="")
    w = csv.DictWriter(text, fieldnames=columns)
    w.writeheader()
    for row in rows:
        w.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in columns})
    write_file(csv_path, text.getvalue())
    write_file(json_path, json.dumps(rows, indent=1, default=str) + "\n")
    return csv_path, json_path


def plot(rows: list[dict], parameters: list, out: Path) -> list[Path]:
    """One PNG per parameter: each metric against it, every seed a dot, the mean a line
    (a log axis for positive values spanning a decade or more)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator
    import numpy as np

    written = []
    for p in parameters:
        col = f"param {p.path}"
        numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in p.values)
        values = list(p.values)
        logx = numeric and min(values) > 0 and max(values) / min(values) >= 10
        fig, axes = plt.subplots(2, 3, figsize=(13, 7))
        # a run that reproduced with several models (ETAR and STAR): a series per model
        named_models = list(dict.fromkeys(r["param model"] for r in rows if r.get("param model")))
        models = named_models if named_models and p.path != "model" else [None]
        for ax, (key, label) in zip(axes.ravel(), METRICS):
            for n, model in enumerate(models):
                means = []
                named = "" if model is None else f"{model}: "
                for i, v in enumerate(values):
                    ys = [r.get(key) for r in rows if r.get(col) == v and r.get(key) is not None
                          and not r.get("error") and (model is None or r.get("param model") == model)]
                    x = v if numeric else i
                    ax.scatter([x] * len(ys), ys, s=22, alpha=0.6, color=f"C{2 * n}",
                               label=f"{named}one seed" if i == 0 else None)
                    means.append((x, float(np.mean(ys)) if ys else float("nan")))
                ax.plot([m[0] for m in means], [m[1] for m in means], "-o", ms=3, color=f"C{2 * n + 1}",
                        label=f"{named}mean over seeds")
            if logx:
                ax.set_xscale("log")
                ax.set_xticks(values, [f"{v:g}" for v in values])
            elif not numeric:
                ax.set_xticks(range(len(values)), [str(v) for v in values])
            if key == "phases_chosen":
                ax.yaxis.set_major_locator(MaxNLocator(integer=True))
                top = max([y for line in ax.get_lines() for y in line.get_ydata() if y == y], default=1.0)
                ax.set_ylim(0.5, top + 1.5)
            ax.set_xlabel(p.path)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        axes[0, 0].legend(fontsize=8)
        axes.ravel()[-1].axis("off")
        seeds = sorted({r.get("seed") for r in rows})
        # a run that reproduced with several models is a row per model: count runs, not rows
        runs = {r.get("run") for r in rows}
        failed = {r.get("run") for r in rows if r.get("error")}
        axes.ravel()[-1].text(0.0, 0.9, f"{len(runs)} runs, {len(values)} values x {len(seeds)} seed(s)\n"
                              f"runs that failed to run: {len(failed)}", fontsize=10, va="top")
        fig.suptitle(f"sweep over {p.path}")
        fig.tight_layout()
        path = out / f"{p.path.replace('.', '_').replace('[', '_').replace(']', '')}.png"
        write_via(path, lambda tmp: fig.savefig(tmp, dpi=90, format="png"))
        plt.close(fig)
        written.append(path)
    return written
