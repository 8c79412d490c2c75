"""Progress of long work on a terminal: the episode or run going on, its simulated
time and its real-time factor (tqdm).  Nothing is drawn when stderr is not a
terminal (CI logs, pipes); the runner's one line per episode says it all there."""

from __future__ import annotations

import sys
import time


class EpisodeProgress:
    """A bar over one episode's simulated time (``total_s`` at most)."""

    def __init__(self, label: str, total_s: float, enabled: bool | None = None):
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self._t0 = time.monotonic()
        self._bar = None
        if self.enabled:
            from tqdm import tqdm

            self._bar = tqdm(total=round(total_s, 3), desc=label, unit="sim s", file=sys.stderr, leave=False,
                             bar_format="{desc}: {n:.1f}/{total:.0f} sim s {bar:20}{postfix}", dynamic_ncols=True)

    def update(self, sim_s: float) -> None:
        if self._bar is None:
            return
        wall = time.monotonic() - self._t0
        self._bar.n = round(sim_s, 3)
        self._bar.set_postfix_str(f"{sim_s / wall:.2f}x real time" if wall > 0 else "")

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
