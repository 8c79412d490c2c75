"""The FRI cycle engine on a fake clock: when cycles open and close, in lockstep and realtime."""

import pytest

from services.runtime.bus import FakeClock
from services.runtime.cycle import CycleEngine, EpisodePlan
from services.runtime.loop import Sections

MS = 1_000_000


class Arm:
    """A participant that records when it was asked to measure and to step."""

    cycle_ns = MS

    def __init__(self, clock, work_ns=0, stop_after=None):
        self.clock = clock
        self.sections = Sections("wait", "answers", "step", "measure", "encode", "publish")
        self.answers = set()
        self.opened, self.closed = [], []
        self.seq = 0
        self.work_ns = work_ns
        self.stop_after = stop_after

    def open_cycle(self):
        self.seq += 1
        self.opened.append((self.seq, self.clock.t))
        self.clock.advance(self.work_ns)
        return self.seq, (self.seq - 1) * MS

    def answered(self, names, seq):
        return all((n, seq) in self.answers for n in names)

    def close_cycle(self, stop_on):
        self.closed.append((self.seq, self.clock.t))
        if self.stop_after is not None and len(self.closed) >= self.stop_after:
            return "goal_reached"
        return None


def engine(arm, clock, mode, **plan):
    return CycleEngine(arm, EpisodePlan(**{"max_cycles": 100, **plan}), clock, mode=mode, cycle_ns=MS,
                       answer_timeout_ns=5 * MS)


def test_lockstep_closes_a_cycle_when_its_answers_are_in_and_only_then():
    clock = FakeClock()
    arm = Arm(clock)
    e = engine(arm, clock, "lockstep", answers_from=("command",))
    assert e.tick(clock.t) == 5 * MS  # opened cycle 1; waits for its answer until the timeout
    assert arm.opened == [(1, 0)] and e.awaiting()
    clock.advance(MS // 2)
    e.tick(clock.t)
    assert arm.closed == [] and e.open_seq == 1  # no answer yet: still open
    arm.answers.add(("command", 1))
    e.tick(clock.t)
    assert [s for s, _ in arm.closed] == [1] and e.open_seq == 2 and e.k == 1 and e.missed_answers == 0


def test_lockstep_counts_a_missed_answer_at_the_timeout_or_at_once_when_nothing_more_can_come():
    clock = FakeClock()
    arm = Arm(clock)
    e = engine(arm, clock, "lockstep", answers_from=("command",))
    e.tick(0)
    clock.advance(5 * MS)
    e.tick(clock.t)
    assert e.missed_answers == 1 and [s for s, _ in arm.closed] == [1]
    e.tick(clock.t, quiescent=True)  # cycle 2 unanswered and nothing in flight
    assert e.missed_answers == 2 and [s for s, _ in arm.closed] == [1, 2]


@pytest.mark.parametrize("silent", ["teacher", "ft"])
def test_lockstep_ends_the_episode_when_a_participant_is_silent_twice_in_a_row(silent):
    """In a demonstration the sensor's silence ends it too: its recording is what it is for."""
    clock = FakeClock()
    arm = Arm(clock)
    other = {"teacher": "ft", "ft": "teacher"}[silent]
    e = engine(arm, clock, "lockstep", answers_from=("teacher", "ft"))
    e.tick(0)
    for seq in range(1, 4):  # both answer the first three cycles
        arm.answers |= {("teacher", seq), ("ft", seq)}
        e.tick(clock.t)
    arm.answers.add((other, 4))  # then one goes silent
    clock.advance(5 * MS)
    e.tick(clock.t)
    assert not e.done and e.missed_answers == 1  # one timeout: a slow cycle, not yet a silent participant
    arm.answers.add((other, 5))
    clock.advance(5 * MS)
    e.tick(clock.t)
    assert e.done and e.reason == f"unanswered:{silent}" and e.k == 5 and e.missed_answers == 2
    assert e.tick(clock.t) is None


def test_a_silent_sensor_is_waited_for_once_and_again_when_it_records():
    """Beside the commander, the sensor's record keeps it in step with the arm; a sensor that
    stops costs one timeout, not the episode (the commander's stale estimate holds the arm), and
    once it records a cycle again its records are waited for again."""
    clock = FakeClock()
    arm = Arm(clock)
    e = engine(arm, clock, "lockstep", answers_from=("command", "ft"))
    e.tick(0)
    for seq in range(1, 4):
        arm.answers |= {("command", seq), ("ft", seq)}
        e.tick(clock.t)
    for seq in range(4, 9):  # the sensor stops at cycle 4
        arm.answers.add(("command", seq))
        before = clock.t
        e.tick(clock.t)
        if seq == 4:
            assert e.k == 3 and e.open_seq == 4  # waited for its record...
            clock.advance(5 * MS)
            e.tick(clock.t)
        assert clock.t - before == (5 * MS if seq == 4 else 0)  # ...once: then the command alone closes a cycle
    assert not e.done and e.k == 8 and e.missed_answers == 1
    arm.answers |= {("command", 9), ("ft", 9)}  # it records again
    e.tick(clock.t)
    arm.answers.add(("command", 10))
    e.tick(clock.t)
    assert e.k == 9 and e.open_seq == 10 and e.awaiting()  # cycle 10 waits for its record again
    arm.answers.add(("ft", 10))
    e.tick(clock.t)
    assert e.k == 10 and not e.done and e.missed_answers == 1


def test_lockstep_timeouts_that_are_not_in_a_row_do_not_end_the_episode():
    clock = FakeClock()
    arm = Arm(clock)
    e = engine(arm, clock, "lockstep", answers_from=("command",))
    e.tick(0)
    for seq in range(1, 9):
        if seq % 2:
            clock.advance(5 * MS)  # every other cycle times out
        else:
            arm.answers.add(("command", seq))
        e.tick(clock.t)
    assert not e.done and e.missed_answers == 4 and e.k == 8


def test_lockstep_waits_for_the_estimate_only_on_every_tenth_cycle():
    clock = FakeClock()
    arm = Arm(clock)
    e = engine(arm, clock, "lockstep", answers_from=("command", "phase"))
    for seq in range(1, 13):
        e.tick(clock.t)
        arm.answers.add(("command", seq))
    e.tick(clock.t)
    # seq 1 is stamped 0 ms (a tenth cycle): it needs the phase, which never came
    assert e.k == 0 and e.open_seq == 1
    arm.answers.add(("phase", 1))
    for _ in range(12):
        e.tick(clock.t)
    # seq 11 (stamp 10 ms) waits for its phase again; 2..10 did not need one
    assert e.k == 10 and e.open_seq == 11


def test_settle_runs_exactly_its_cycles_and_stop_on_ends_an_episode():
    clock = FakeClock()
    arm = Arm(clock)
    e = engine(arm, clock, "lockstep", cycles=3, max_cycles=3)
    while not e.done:
        e.tick(clock.t)
    assert e.reason == "settled" and e.k == 3 and len(arm.opened) == 3
    arm = Arm(clock, stop_after=4)
    e = engine(arm, clock, "lockstep", stop_on="goal_reached")
    while not e.done:
        e.tick(clock.t)
    assert e.reason == "goal_reached" and e.k == 4
    arm = Arm(clock)
    e = engine(arm, clock, "lockstep", max_cycles=7)
    while not e.done:
        e.tick(clock.t)
    assert e.reason == "elapsed" and e.k == 7  # nothing to stop on: running the whole time is the plan


def test_realtime_measures_at_each_deadline_and_steps_as_soon_as_the_answer_is_in():
    clock = FakeClock(1000 * MS)
    arm = Arm(clock)
    e = engine(arm, clock, "realtime", answers_from=("command",))
    t0 = clock.t
    assert e.tick(clock.t) == t0 + MS  # cycle 1 opened at its deadline, the next deadline returned
    clock.advance(300_000)
    arm.answers.add(("command", 1))
    assert e.tick(clock.t) == t0 + MS
    assert arm.closed == [(1, t0 + 300_000)]  # stepped when the answer came, not at the deadline
    clock.t = t0 + MS
    e.tick(clock.t)
    assert arm.opened[-1] == (2, t0 + MS)  # the measurement goes out at the cycle's start
    clock.t = t0 + 2 * MS  # no answer to cycle 2
    e.tick(clock.t)
    assert arm.closed[-1] == (2, t0 + 2 * MS) and arm.opened[-1] == (3, t0 + 2 * MS)
    assert e.timing.misses == 0 and e.timing.cycles == 3


def test_realtime_skips_the_deadlines_an_overrun_lost_instead_of_bursting():
    clock = FakeClock(0)
    arm = Arm(clock, work_ns=2_500_000)  # measuring takes 2.5 cycles
    e = engine(arm, clock, "realtime")
    nxt = e.tick(clock.t)
    assert nxt == 3 * MS and e.timing.misses == 1  # deadlines 1 and 2 ms are gone
    clock.t = nxt
    e.tick(clock.t)
    assert arm.opened[-1] == (2, 3 * MS) and e.timing.longest_miss_run == 2


def test_stop_closes_the_open_cycle_instead_of_leaving_it_measured_but_unapplied():
    clock = FakeClock()
    arm = Arm(clock)
    e = engine(arm, clock, "lockstep", answers_from=("command",))
    e.tick(0)
    e.stop()
    assert e.done and e.reason == "stopped" and arm.closed == [(1, 0)] and e.missed_answers == 1
    assert e.tick(0) is None


def test_a_plan_that_makes_no_sense_is_refused():
    with pytest.raises(ValueError, match="unknown participants"):
        EpisodePlan(max_cycles=10, answers_from=("cmd",))
    with pytest.raises(ValueError, match="stop_on"):
        EpisodePlan(max_cycles=10, stop_on="goal")
    with pytest.raises(ValueError, match="max_cycles"):
        EpisodePlan(max_cycles=0)


def test_the_robot_is_woken_only_by_the_answers_its_episode_waits_for():
    """Every answer is kept (the FRI link and the report read them), but only an awaited
    one wakes the engine's thread: over Zenoh the sensor's answer to each cycle of a
    demonstration, which waits for the teacher alone, woke it for nothing."""
    from services.nodes.robot import RobotConfig, RobotNode

    class Bus:
        def publish(self, *a, **k):
            pass

    node = RobotNode(RobotConfig(), Bus(), FakeClock())
    on = {s.topic: s.handler for s in node.subscriptions}
    node.inbox.awaited = frozenset({"teacher"})
    before = node.inbox.arrivals
    on["ft/wrench"]({"seq": 7}, 1, b"")
    assert node.inbox.arrivals == before and node.answered(["ft"], 7)
    on["teacher/wrench"]({"seq": 7}, 2, b"")
    assert node.inbox.arrivals == before + 1 and node.answered(["ft", "teacher"], 7)
