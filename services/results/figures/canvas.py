"""What every figure is drawn with: matplotlib without a display, a colour per phase, the
changes of a phase sequence, millimetres for positions, and one way to save a figure."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.runtime.files import write_via

MM = 1e3  # m -> mm, for the axes that say [mm]
UNMATCHED = (0.8, 0.8, 0.8, 1.0)  # a true phase no learned phase was matched to


def pyplot():
    """matplotlib's pyplot, drawing to files only (Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def phase_colours(k: int):
    """One colour per phase, the same in every figure."""
    plt = pyplot()
    return [plt.get_cmap("tab10")(i % 10) for i in range(k)]


def boundaries(labels) -> list:
    """The indices at which a phase sequence changes."""
    labels = np.asarray(labels)
    return list(np.flatnonzero(np.diff(labels)) + 1)


def save(fig, path: Path, laid_out: bool = False) -> Path:
    """Write ``fig`` to ``path`` and let it go.  ``laid_out``: the axes were placed by hand
    (tight_layout misjudges 3-D axes): crop the picture to what is drawn instead."""
    if not laid_out:
        fig.tight_layout()
    try:
        crop = dict(bbox_inches="tight", pad_inches=0.15) if laid_out else {}
        write_via(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png", **crop))
    finally:
        pyplot().close(fig)
    return path
