"""The thesis' figures (section 6) from a finished run: ``etar-bench figures RUN_DIR``.

Every run writes them into ``RUN_DIR/figures/`` too.  One PNG per figure, titled,
axes labelled with units, named after what it shows:

- ``demonstrations_position_and_force.png``: each demonstration's tool position
  and contact force over time (thesis fig. 13, 21);
- ``bic_by_phase_count.png``: the selection criterion against the number of
  phases, per demonstration and pooled (fig. 14, 22);
- ``forward_variable_demonstrations.png``: the normalised forward variable alpha
  over each demonstration, the true phase boundaries dashed (fig. 15a, 23, 24a);
- ``tool_path_by_phase.png``: the tool path in 3-D coloured by the estimated
  (Viterbi) phase (fig. 15b, 24b);
- ``prediction_error_by_step.png``: per step of the first demonstration, the
  one-step prediction error of every phase's parameters, true boundaries dashed
  (fig. 16-19, 28b/c);
- ``prediction_error_by_phase.png``: the K x K bars E_rho_i(theta_j) (fig. 20, 29);
- ``reproduction_NN_force_phase_alpha.png`` (the first reproduction): the force
  feature, the estimated phase and alpha over time, with the commanded phase
  switches (fig. 25).

What a figure needs and the run does not have (no demonstrations, a fixed phase
count: no selection scores) is skipped with the reason.  Reads the run's
report.json, model.json and recordings; writes nothing else.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from etar.analysis import prediction_errors
from etar.comparison import filtered_messages
from etar.task import load_task
from services.recordings.demonstrations import load_demonstration
from services.recordings.reader import read_episode

FIGURES_DIR = "figures"


class FiguresError(ValueError):
    """A run directory the figures cannot be drawn from (names the file)."""


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _phase_colors(k: int):
    plt = _plt()
    return [plt.get_cmap("tab10")(i % 10) for i in range(k)]


def _boundaries(labels) -> list:
    labels = np.asarray(labels)
    return list(np.flatnonzero(np.diff(labels)) + 1)


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    return path


def demonstrations_figure(demos, out: Path) -> Path:
    plt = _plt()
    fig, axes = plt.subplots(2, 3, figsize=(12, 6), sharex=True)
    for i, d in enumerate(demos):
        t = d["t"] - d["t"][0]
        for a in range(3):
            axes[0, a].plot(t, d["states"][:, a] * 1e3, lw=1, label=f"demonstration {i}")
            axes[1, a].plot(t, d["forces"][:, a], lw=1)
    for a, name in enumerate("xyz"):
        axes[0, a].set_title(f"tool position {name}")
        axes[0, a].set_ylabel(f"{name} [mm]")
        axes[1, a].set_title(f"contact force F{name}")
        axes[1, a].set_ylabel(f"F{name} [N]")
        axes[1, a].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Demonstrations: tool position and contact force (thesis fig. 13, 21)")
    return _save(fig, out / "demonstrations_position_and_force.png")


def demonstration_figure(demo: dict, path: Path, title: str = "", phase_names=()) -> Path:
    """One demonstration (``load_demonstration``'s arrays): the 3-D tool path coloured by the
    true phase, beside the tool position and the (tared) force in base axes over time
    (thesis fig. 13 and 15b)."""
    plt = _plt()
    p, t = demo["states"][:, :3], demo["t"]
    # a sample's phase is the phase of the step into it (the first sample: the first step's)
    ph = np.concatenate([demo["phases"][:1], demo["phases"]]).astype(int)
    names = list(phase_names) or [f"phase {k}" for k in range(int(ph.max()) + 1)]
    colours = _phase_colors(int(ph.max()) + 1)
    fig = plt.figure(figsize=(13, 5.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    for k in np.unique(ph):
        sel = ph == k
        ax.scatter(p[sel, 0], p[sel, 1], p[sel, 2], s=3, color=colours[k], label=names[k])
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.legend(loc="upper left")
    ax.set_title(title or "tool path (tip centre), coloured by true phase")
    axp = fig.add_subplot(2, 2, 2)
    axf = fig.add_subplot(2, 2, 4, sharex=axp)
    for i, c in enumerate("xyz"):
        axp.plot(t, p[:, i], label=c)
        axf.plot(t, demo["forces"][:, i], label=f"F{c}")
    for ax_ in (axp, axf):
        for b in _boundaries(ph):
            ax_.axvline(t[b], color="k", lw=0.8, ls="--")
        ax_.legend(loc="upper right", fontsize=8)
        ax_.grid(alpha=0.3)
    axp.set_ylabel("position [m]")
    axf.set_ylabel("force on tool [N]")
    axf.set_xlabel("time [s]  (dashed: true phase changes)")
    return _save(fig, Path(path))


def bic_figure(selection: dict, out: Path) -> Path | str:
    per = selection.get("per_demonstration") or []
    pooled = selection.get("scores") or {}
    if not per and not pooled:
        return f"no selection scores (phase count {selection.get('criterion', 'fixed')})"
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    crit = str(selection.get("criterion", "bic")).upper()
    for i, d in enumerate(per):
        ks = sorted(d["scores"], key=int)
        ax.plot([int(k) for k in ks], [d["scores"][k] for k in ks], "o-", lw=1, ms=3, label=f"demonstration {i}")
    if pooled:
        ks = sorted(pooled, key=int)
        ax.plot([int(k) for k in ks], [pooled[k] for k in ks], "ks-", lw=2, label="pooled")
    ax.axvline(selection["best"], color="grey", ls="--", lw=1, label=f"chosen: {selection['best']}")
    ax.set_xlabel("number of phases K")
    ax.set_ylabel(f"{crit} (lower is better)")
    ax.set_title(f"{crit} against the number of phases\n(thesis fig. 14, 22)")
    ax.legend(fontsize=7)
    return _save(fig, out / "bic_by_phase_count.png")


def forward_figure(model, demos, out: Path) -> Path:
    plt = _plt()
    colors = _phase_colors(model.n_phases)
    fig, axes = plt.subplots(len(demos), 1, figsize=(10, 1.8 * len(demos) + 1), sharex=False, squeeze=False)
    for i, d in enumerate(demos):
        ax = axes[i, 0]
        alpha = filtered_messages(model, d["states"], d["forces"])
        t = d["t"][1:] - d["t"][0]
        for k in range(model.n_phases):
            ax.plot(t, alpha[:, k], color=colors[k], lw=1.2, label=f"phase {k}")
        for b in _boundaries(d["phases"]):
            ax.axvline(t[b], color="black", ls="--", lw=0.8)
        ax.set_ylim(-0.05, 1.05)
        ax.set_ylabel(f"demo {i}\nalpha")
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=7, ncol=model.n_phases, loc="upper right")
    fig.suptitle("Normalised forward variable over each demonstration; dashed: true phase boundaries "
                 "(thesis fig. 15a, 23, 24a)")
    return _save(fig, out / "forward_variable_demonstrations.png")


def path_figure(model, demos, out: Path) -> Path:
    plt = _plt()
    colors = _phase_colors(model.n_phases)
    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    for d in demos:
        s = d["states"][:, :3] * 1e3
        phases = model.viterbi(d["states"], d["forces"])
        for k in range(model.n_phases):
            sel = np.flatnonzero(phases == k) + 1
            ax.scatter(s[sel, 0], s[sel, 1], s[sel, 2], s=3, color=colors[k])
    for k in range(model.n_phases):
        ax.scatter([], [], [], color=colors[k], label=f"phase {k}")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")
    ax.legend(fontsize=7)
    ax.set_title("Tool path coloured by the estimated phase\n(thesis fig. 15b, 24b)")
    return _save(fig, out / "tool_path_by_phase.png")


def prediction_figures(model, demos, out: Path) -> list[Path]:
    plt = _plt()
    colors = _phase_colors(model.n_phases)
    K = model.n_phases
    d = demos[0]
    s, f = d["states"], d["forces"]
    A, B = np.asarray(model.A), np.asarray(model.B)
    u = np.hstack([f[:-1], np.ones((len(s) - 1, 1))])
    t = d["t"][1:] - d["t"][0]
    fig, axes = plt.subplots(K, 1, figsize=(10, 1.9 * K + 1), sharex=True, squeeze=False)
    for j in range(K):
        err = np.linalg.norm(s[:-1] @ A[j].T + u @ B[j].T - s[1:], axis=1) * 1e3
        axes[j, 0].bar(t, err, width=(t[1] - t[0]) if len(t) > 1 else 0.01, color=colors[j])
        for b in _boundaries(d["phases"]):
            axes[j, 0].axvline(t[b], color="black", ls="--", lw=0.8)
        axes[j, 0].set_ylabel(f"theta_{j}\n|error| [mm]")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle("One-step prediction error of each phase's parameters over demonstration 0; dashed: true "
                 "boundaries (thesis fig. 16-19)")
    by_step = _save(fig, out / "prediction_error_by_step.png")

    # E_rho_i(theta_j) over the model's own (Viterbi) segmentation, as the thesis estimated it
    pe = prediction_errors(model, [(x["states"], x["forces"]) for x in demos])
    fig, ax = plt.subplots(figsize=(8, 4.5))
    width = 0.8 / K
    for j in range(K):
        ax.bar(np.arange(K) + j * width, pe.mse[:, j] * 1e6, width=width, color=colors[j], label=f"theta_{j}")
    ax.set_xticks(np.arange(K) + 0.4 - width / 2)
    ax.set_xticklabels([f"steps of phase {i}\n({pe.count[i]} steps)" for i in range(K)])
    ax.set_ylabel("mean squared one-step error [mm^2]")
    ax.set_yscale("log")
    ax.legend(fontsize=7, title="parameters")
    ax.set_title("E_rho_i(theta_j): each phase's steps predicted with each phase's parameters\n"
                 "(thesis fig. 20, 29)")
    return [by_step, _save(fig, out / "prediction_error_by_phase.png")]


def reproduction_figure(path: Path, index: int, model, state: str, features: str, out: Path) -> Path | str:
    plt = _plt()
    try:
        d = load_demonstration(path, state=state, features=features, allow_incomplete=True)
    except (OSError, ValueError) as exc:
        return f"reproduction {index}: {exc}"
    estimates, commanded = [], []
    for m in read_episode(path).messages:
        if m.topic not in ("/estimator/phase", "/robot/command"):
            continue
        try:
            msg = json.loads(m.payload)
        except ValueError:
            continue
        if m.topic == "/estimator/phase":
            estimates.append((msg["stamp_ns"] / 1e9, msg["phase"], msg["posterior"]))
        else:
            commanded.append((msg["stamp_ns"] / 1e9, msg["phase"]))
    if not estimates:
        return f"reproduction {index}: no phase estimates recorded"
    t0 = d["t"][0]
    colors = _phase_colors(model.n_phases)
    fig, axes = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True)
    for a, name in enumerate("xyz"):
        axes[0].plot(d["t"] - t0, d["forces"][:, a], lw=1, label=f"F{name}")
    axes[0].set_ylabel("force feature [N]")
    axes[0].legend(fontsize=7)
    te = np.array([e[0] for e in estimates]) - t0
    axes[1].step(te, [e[1] for e in estimates], where="post", color="black", lw=1.2, label="estimated phase")
    commanded.sort()
    tc = np.array([c[0] for c in commanded]) - t0
    pc = np.array([c[1] for c in commanded])
    switches = np.flatnonzero(np.diff(pc)) + 1
    for i in switches:
        for ax in axes:
            ax.axvline(tc[i], color="red", ls=":", lw=0.9)
    axes[1].set_ylabel("phase")
    axes[1].set_yticks(range(model.n_phases))
    axes[1].legend(fontsize=7)
    post = np.array([e[2] for e in estimates])
    for k in range(post.shape[1]):
        axes[2].plot(te, post[:, k], color=colors[k], lw=1.2, label=f"phase {k}")
    axes[2].set_ylabel("alpha")
    axes[2].set_xlabel("time [s]")
    axes[2].legend(fontsize=7, ncol=post.shape[1])
    fig.suptitle(f"Reproduction {index}: force feature, estimated phase and alpha; dotted red: the commanded "
                 "phase switches (thesis fig. 25)")
    return _save(fig, out / f"reproduction_{index:02d}_force_phase_alpha.png")


def in_run(run_dir: Path, path) -> Path:
    """A path report.json names: relative to the run's folder unless absolute."""
    return Path(path) if Path(path).is_absolute() else run_dir / path


def read_run_report(run_dir: Path) -> dict:
    """A finished run's report.json; FiguresError naming the file if there is none."""
    report_path = run_dir / "report.json"
    try:
        report = json.loads(report_path.read_text())
    except FileNotFoundError:
        raise FiguresError(f"{report_path}: missing (is {run_dir} a finished run's folder?)") from None
    except (OSError, ValueError) as exc:
        raise FiguresError(f"{report_path}: {exc}") from None
    if not isinstance(report, dict) or "learning" not in report:
        raise FiguresError(f"{report_path}: not a run report (no 'learning')")
    return report


def write_figures(run_dir, progress=None) -> tuple[list[Path], list[str]]:
    """Every figure the run has data for, into RUN_DIR/figures/: (files written, what was
    skipped and why)."""
    run_dir = Path(run_dir)
    report = read_run_report(run_dir)
    out = run_dir / FIGURES_DIR
    out.mkdir(exist_ok=True)
    say = progress or (lambda _m: None)
    written, skipped = [], []
    model_path = report["learning"].get("model")
    if not model_path:
        return written, ["no learned model in the run"]
    task = load_task(in_run(run_dir, model_path))
    model = task.model
    demos = []
    for d in report.get("demonstrations", []):
        p = in_run(run_dir, d["path"])
        try:
            demos.append(load_demonstration(p, state=task.state, features=task.features, allow_incomplete=True))
        except (OSError, ValueError) as exc:
            skipped.append(f"demonstration {p.name}: {exc}")
    if demos:
        say(f"figures: {len(demos)} demonstrations")
        written.append(demonstrations_figure(demos, out))
        written.append(forward_figure(model, demos, out))
        written.append(path_figure(model, demos, out))
        written += prediction_figures(model, demos, out)
    else:
        skipped.append("no demonstrations: their figures are not drawn")
    bic = bic_figure(report["learning"].get("selection") or {}, out)
    (written if isinstance(bic, Path) else skipped).append(bic)
    repro = report.get("reproductions") or []
    if repro:
        p = in_run(run_dir, repro[0]["path"])
        fig = reproduction_figure(p, 0, model, task.state, task.features, out)
        (written if isinstance(fig, Path) else skipped).append(fig)
    return written, skipped
