"""A reproduction over time (thesis fig. 25): the force feature, the estimated phase beside
the true phase it is scored against, and the forward variable alpha, with the commanded
phase switches."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from etar.metrics import score_segmentation
from services.results.decoding import ReproductionTrace
import services.results.figures.canvas as canvas
from services.results.figures.phases import phase_labels, true_label


def _runs(t: np.ndarray, v: np.ndarray, t_end: float) -> list[tuple[float, float, int]]:
    """(start, width, value) of each run of equal ``v`` over times ``t``; the last ends at t_end."""
    if len(v) == 0:
        return []
    cuts = [0, *canvas.boundaries(v), len(v)]
    ends = [*t[cuts[1:-1]], t_end]
    return [(float(t[a]), float(e - t[a]), int(v[a])) for a, e in zip(cuts[:-1], ends)]


def reproduction_figure(trace: ReproductionTrace, index: int, model, out: Path, phase_to_truth=None,
                        true_names=()) -> Path | str:
    """Reproduction ``index``: the force feature, the estimated phase beside the true phase
    it is scored against (the simulator's label of the same robot cycle, ``/robot/contact``
    ``true_phase``, as the report scores it), and alpha; ``phase_to_truth``: which true phase
    each learned phase is (the demonstrations' matching, as the report uses it).  What
    cannot be drawn is returned as the reason."""
    estimates = trace.estimates
    if not estimates:
        return f"reproduction {index}: no phase estimates recorded"
    K = model.n_phases
    mapping = {int(k): int(v) for k, v in (phase_to_truth or {}).items()}
    labels = phase_labels(K, mapping, true_names)
    t0 = trace.t[0]
    colours = canvas.phase_colours(K)
    te = np.array([e[0] for e in estimates]) - t0
    est = np.array([e[1] for e in estimates], dtype=int)
    t_end = float(max(te[-1], trace.t[-1] - t0))
    # the true phase of each estimate's robot cycle: the pairs the report scores
    scored = [i for i, e in enumerate(estimates) if e[3] in trace.truth_by_seq]
    true = np.array([trace.truth_by_seq[estimates[i][3]] for i in scored], dtype=int)

    torque = trace.forces.shape[1] >= 6  # force_torque features: the torque panel too
    ratios = [3, 2.2, 1.6, 3] if torque else [3, 1.6, 3]
    fig, axes = canvas.pyplot().subplots(len(ratios), 1, figsize=(10, 2 * len(ratios) + 1.5), sharex=True,
                                         gridspec_kw={"height_ratios": ratios})
    _force_panels(axes, trace.t, trace.forces, t0, torque)
    accuracy = _phase_strips(axes[-2], te, est, scored, true, t_end, mapping, colours, labels, true_names)
    _alpha_panel(axes[-1], te, np.array([e[2] for e in estimates]), colours, labels)
    commanded = trace.commanded
    tc = np.array([c[0] for c in commanded]) - t0
    pc = np.array([c[1] for c in commanded])
    for i in np.flatnonzero(np.diff(pc)) + 1:
        for a in axes:
            a.axvline(tc[i], color="red", ls=":", lw=0.9)
    how = (f"online phase accuracy {accuracy:.1%} over {len(true)} estimates" if accuracy is not None else
           "no learned-to-true phase mapping: not scored" if len(true) else "no true phase recorded")
    fig.suptitle(f"Reproduction {index}: force feature, estimated against true phase, alpha ({how})\n"
                 "dotted red: the commanded phase switches (thesis fig. 25)")
    return canvas.save(fig, out / f"reproduction_{index:02d}_force_phase_alpha.png")


def _force_panels(axes, t, forces, t0: float, torque: bool) -> None:
    for a, name in enumerate("xyz"):
        axes[0].plot(t - t0, forces[:, a], lw=1, label=f"F{name}")
        if torque:
            axes[1].plot(t - t0, forces[:, 3 + a], lw=1, label=f"T{name}")
    axes[0].set_ylabel("force on tool [N]")
    if torque:
        axes[1].set_ylabel("torque on tool [N m]")
    for ax in axes[:2 if torque else 1]:
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)


def _phase_strips(ax, te, est, scored, true, t_end, mapping, colours, labels, true_names) -> float | None:
    """Estimated (top), true (middle), where they disagree (bottom); the accuracy the report
    would give these pairs, None without a mapping or a true phase."""
    from matplotlib.patches import Patch

    K = len(labels)
    tt = te[scored]
    truth_colour = {v: colours[k] for k, v in mapping.items() if k < K}
    for start, width, k in _runs(te, est, t_end):
        ax.broken_barh([(start, width)], (2.1, 0.8), facecolors=[colours[k % len(colours)]])
    true_seen = sorted(set(true.tolist()))
    for start, width, v in _runs(tt, true, t_end):
        ax.broken_barh([(start, width)], (1.1, 0.8), facecolors=[truth_colour.get(v, canvas.UNMATCHED)],
                       hatch=None if v in truth_colour else "//", edgecolor="white" if v in truth_colour else "grey")
    accuracy = None
    if len(true) and mapping:
        accuracy = score_segmentation(true, est[scored], mapping=mapping).accuracy
        wrong = np.array([mapping.get(int(k), -1) for k in est[scored]]) != true
        for start, width, w in _runs(tt, wrong.astype(int), t_end):
            if w:
                ax.broken_barh([(start, width)], (0.35, 0.5), facecolors=["crimson"])
    ax.set_ylim(0.2, 3.0)
    ax.set_yticks([0.6, 1.5, 2.5])
    ax.set_yticklabels(["wrong", "true phase", "estimated phase"], fontsize=8)
    ax.grid(axis="x", alpha=0.3)
    present = sorted(set(est.tolist()) | {k for k, v in mapping.items() if v in true_seen})
    handles = [Patch(color=colours[k], label=labels[k]) for k in range(K) if k in present or k in mapping]
    handles += [Patch(facecolor=canvas.UNMATCHED, hatch="//", edgecolor="grey",
                      label=f"{true_label(v, true_names)}: no learned phase") for v in true_seen
                if v not in truth_colour]
    if mapping:
        handles.append(Patch(color="crimson", label="estimate != true phase"))
    ax.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.005, 1.0), borderaxespad=0)
    return accuracy


def _alpha_panel(ax, te, post, colours, labels) -> None:
    for k in range(post.shape[1]):
        ax.plot(te, post[:, k], color=colours[k % len(colours)], lw=1.2,
                label=labels[k] if k < len(labels) else f"phase {k}")
    ax.set_ylabel("alpha [-]")
    ax.set_ylim(-0.05, 1.05)
    ax.set_xlabel("time [s]")
    ax.legend(fontsize=7, loc="center left")
    ax.grid(alpha=0.3)
