"""Pictures of demonstrations (matplotlib, no screen needed)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

PHASE_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b")


def plot_demonstration(demo, path, title: str = "", phase_names=None) -> None:
    """3-D tool path coloured by the true phase, beside the tool position and
    the (tared) force in base axes over time - thesis fig. 13 and 15b."""
    p = demo.positions
    ph = demo.true_phase
    names = phase_names or [f"phase {k}" for k in range(int(ph.max()) + 1)]
    fig = plt.figure(figsize=(13, 5.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    for k in np.unique(ph):
        sel = ph == k
        ax.scatter(p[sel, 0], p[sel, 1], p[sel, 2], s=3, color=PHASE_COLOURS[k % 6], label=names[k])
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.legend(loc="upper left")
    ax.set_title(title or "tool path (tip centre), coloured by true phase")
    axp = fig.add_subplot(2, 2, 2)
    axf = fig.add_subplot(2, 2, 4, sharex=axp)
    for i, c in enumerate("xyz"):
        axp.plot(demo.t, p[:, i], label=c)
        axf.plot(demo.t, demo.wrench_base[:, i], label=f"F{c}")
    for ax_ in (axp, axf):
        for k in np.unique(ph)[1:]:
            ax_.axvline(demo.t[np.argmax(ph == k)], color="k", lw=0.8, ls="--")
        ax_.legend(loc="upper right", fontsize=8)
        ax_.grid(alpha=0.3)
    axp.set_ylabel("position [m]")
    axf.set_ylabel("force on tool [N]")
    axf.set_xlabel("time [s]  (dashed: true phase changes)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
