"""The true phase of a task, from what the tool tip touches (physics ground truth).

Labels never go back within an episode: a tip lifting off a plate for a
millisecond is still sliding along it.  The teacher uses these during
demonstrations and the robot service during reproductions, so both label the
same way.
"""

from __future__ import annotations


class ValleyLabeler:
    """0 free motion (nothing touched yet), 1 sliding along a plate (from the
    first touch of a plate), 2 sliding along the groove (from the first touch
    of the other plate, which only the groove's bottom allows)."""

    n_phases = 3
    names = ("free motion", "sliding along a plate", "sliding along the groove")

    def __init__(self):
        self.phase = 0
        self._first_plate = None

    def update(self, touching) -> int:
        if self.phase == 2 or not touching:  # the last phase is final; touching nothing changes nothing
            return self.phase
        plates = {name for name in touching if name.startswith("plate")}
        if plates:
            if self.phase == 0:
                self.phase = 1
                self._first_plate = min(plates)
            if self.phase == 1 and plates - {self._first_plate}:
                self.phase = 2
        return self.phase


class CouplerLabeler:
    """0 approach, 1 coupling (from the first touch of the coupler)."""

    n_phases = 2
    names = ("approach", "coupling")

    def __init__(self):
        self.phase = 0

    def update(self, touching) -> int:
        if any(t.startswith("coupler") for t in touching):
            self.phase = 1
        return self.phase


LABELERS = {"valley": ValleyLabeler, "hose_coupler": CouplerLabeler}
