"""What was learned from the demonstrations: how the number of phases was chosen (thesis
fig. 14, 22), the forward variable over each demonstration (fig. 15a, 23, 24a), and each
phase's one-step prediction errors (fig. 16-20, 28, 29)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from etar.analysis import prediction_errors
from etar.comparison import filtered_messages
import services.results.figures.canvas as canvas
from services.results.figures.phases import phase_labels


def bic_figure(selection: dict, out: Path) -> Path | str:
    per = selection.get("per_demonstration") or []
    pooled = selection.get("scores") or {}
    if not per and not pooled:
        return f"no selection scores (phase count {selection.get('criterion', 'fixed')})"
    plt = canvas.pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    crit = str(selection.get("criterion", "bic")).upper()
    for i, d in enumerate(per):
        ks = sorted(d["scores"], key=int)
        ax.plot([int(k) for k in ks], [d["scores"][k] for k in ks], "o-", lw=1, ms=3, label=f"demonstration {i}")
    if pooled:
        ks = sorted(pooled, key=int)
        ax.plot([int(k) for k in ks], [pooled[k] for k in ks], "ks-", lw=2, label="pooled")
    ax.axvline(selection["best"], color="grey", ls="--", lw=1, label=f"chosen: {selection['best']}")
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_xlabel("number of phases K [-]")
    ax.set_ylabel(f"{crit} [-] (lower is better)")
    ax.set_title(f"{crit} against the number of phases\n(thesis fig. 14, 22)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return canvas.save(fig, out / "bic_by_phase_count.png")


def forward_figure(model, demos, out: Path, labels=None) -> Path:
    plt = canvas.pyplot()
    colors = canvas.phase_colours(model.n_phases)
    labels = labels or phase_labels(model.n_phases)
    fig, axes = plt.subplots(len(demos), 1, figsize=(10, 1.8 * len(demos) + 1.4), sharex=False, squeeze=False)
    for i, d in enumerate(demos):
        ax = axes[i, 0]
        alpha = filtered_messages(model, d["states"], d["forces"])
        t = d["t"][1:] - d["t"][0]
        for k in range(model.n_phases):
            ax.plot(t, alpha[:, k], color=colors[k], lw=1.2, label=labels[k])
        for b in canvas.boundaries(d["phases"]):
            ax.axvline(t[b], color="black", ls="--", lw=0.8)
        ax.set_ylim(-0.05, 1.05)
        ax.set_ylabel(f"demo {i}\nalpha [-]")
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=8, ncol=min(model.n_phases, 4), loc="lower center", bbox_to_anchor=(0.5, 1.0),
                      frameon=False)
    fig.suptitle("Normalised forward variable over each demonstration; dashed: true phase boundaries "
                 "(thesis fig. 15a, 23, 24a)")
    return canvas.save(fig, out / "forward_variable_demonstrations.png")


def prediction_figures(model, demos, out: Path, labels=None) -> list[Path]:
    plt = canvas.pyplot()
    colors = canvas.phase_colours(model.n_phases)
    K = model.n_phases
    labels = labels or phase_labels(K)
    d = demos[0]
    s, f = d["states"], d["forces"]
    A, B = np.asarray(model.A), np.asarray(model.B)
    u = np.hstack([f[:-1], np.ones((len(s) - 1, 1))])
    t = d["t"][1:] - d["t"][0]
    fig, axes = plt.subplots(K, 1, figsize=(10, 1.9 * K + 1), sharex=True, squeeze=False)
    for j in range(K):
        # the position part of the state (a pose's turn is in rad, not mm)
        err = np.linalg.norm((s[:-1] @ A[j].T + u @ B[j].T - s[1:])[:, :3], axis=1) * canvas.MM
        # a bar per step, as one filled outline: a thousand bar patches took matplotlib ~0.5 s a phase
        half = ((t[1] - t[0]) if len(t) > 1 else 0.01) / 2
        axes[j, 0].stairs(err, np.append(t - half, t[-1] + half), fill=True, color=colors[j])
        for b in canvas.boundaries(d["phases"]):
            axes[j, 0].axvline(t[b], color="black", ls="--", lw=0.8)
        axes[j, 0].set_ylabel(f"theta_{j}\n|position error| [mm]")
        axes[j, 0].set_title(f"parameters of {labels[j]}", fontsize=9, loc="left")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle("One-step prediction error of each phase's parameters over demonstration 0; dashed: true "
                 "boundaries (thesis fig. 16-19)")
    by_step = canvas.save(fig, out / "prediction_error_by_step.png")

    # E_rho_i(theta_j) over the model's own (Viterbi) segmentation, as the thesis estimated it
    pe = prediction_errors(model, [(x["states"], x["forces"]) for x in demos])
    fig, ax = plt.subplots(figsize=(9, 4.8))
    width = 0.8 / K
    for j in range(K):
        ax.bar(np.arange(K) + j * width, pe.mse[:, j] * canvas.MM ** 2, width=width, color=colors[j],
               label=f"theta_{j}: {labels[j]}")
    ax.set_xticks(np.arange(K) + 0.4 - width / 2)
    ax.set_xticklabels([f"steps of {labels[i]}\n({pe.count[i]} steps)" for i in range(K)], fontsize=8)
    pose = model.n_state > 3
    ax.set_ylabel("mean squared one-step error\n" + ("[mm^2 + mrad^2]" if pose else "[mm^2]"))
    ax.set_yscale("log")
    ax.legend(fontsize=7, title="parameters")
    ax.set_title("E_rho_i(theta_j): each phase's steps predicted with each phase's parameters\n"
                 "(thesis fig. 20, 29)")
    return [by_step, canvas.save(fig, out / "prediction_error_by_phase.png")]
