"""Python's cyclic garbage collector kept out of the 1 kHz path of a realtime process.

Measured with ``gc.callbacks`` in one process holding the whole cell (two in-process
smoke reproductions): a young-generation collection takes 0.1-1.5 ms, a middle one about 1 ms,
a full one 40-70 ms over the ~180 000 objects MuJoCo, Pinocchio, numba and the
nodes leave tracked.  Triggered by allocation counts, they land in FRI cycles at
random: a middle collection every ~100 ms is 1 % of cycles missed, a full one a
run of dozens.  A realtime process therefore collects where a pause costs nothing
(after start-up, after each control request, after each episode), freezes what
survived (``gc.freeze``: never scanned again), and does not collect by itself in
between.  Almost every object of a cycle is freed by reference counting; what a
cycle would leave as cyclic garbage is bounded by ``relieve``: past ``BACKLOG``
net new tracked objects, the young generation is collected at once (a leak then
shows as occasional misses, not as memory growing without bound).
"""

from __future__ import annotations

import gc

BACKLOG = 20_000  # net new tracked objects before relieve() collects the young generation


class PausedCollector:
    def __init__(self, backlog: int = BACKLOG):
        self.backlog = int(backlog)
        self.relieved = 0  # young collections relieve() had to make: a leak if it grows
        self.active = False

    def start(self) -> None:
        gc.collect()
        gc.freeze()
        gc.disable()
        self.active = True

    def between_episodes(self) -> None:
        """Collect and freeze now, where a pause costs nothing."""
        if self.active:
            gc.collect()
            gc.freeze()

    def relieve(self) -> None:
        if self.active and gc.get_count()[0] > self.backlog:
            gc.collect(0)
            self.relieved += 1

    def stop(self) -> None:
        if self.active:
            self.active = False
            gc.unfreeze()
            gc.enable()
