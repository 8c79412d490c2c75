"""What an episode's cycles wait for (services.run.episode.Episodes.run)."""

import pytest

from services.run.episode import Episodes


class Cell:
    def __init__(self):
        self.asked = []

    def run_episode(self, answers_from, stop_on, max_seconds, progress=None, listening=()):
        self.asked.append(list(answers_from))
        return {"reason": "teacher_done"}


@pytest.mark.parametrize("clock, answers, waited", [
    ("lockstep", ["teacher"], ["teacher", "ft"]), ("lockstep", ["command"], ["command", "ft"]),
    ("lockstep", ["command", "ft"], ["command", "ft"]), ("lockstep", [], []),
    ("realtime", ["teacher"], ["teacher"]), ("realtime", ["command"], ["command"])])
def test_a_lockstep_episode_waits_for_the_sensors_record_of_every_cycle(clock, answers, waited):
    """In lockstep a cycle waits for the sensor too: run ahead of it, a foreign peer's copy of a
    later robot/contact reached the sensor before the real ones, which it dropped as older, and
    a replay changed the run's results (bench/replay_duplicates.py).  Realtime closes a cycle on
    what it applies; a served episode (no answers) waits for nothing."""
    cell = Cell()
    Episodes(cell, clock=clock).run(answers, None, 1.0)
    assert cell.asked == [waited]
