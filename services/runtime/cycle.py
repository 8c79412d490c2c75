"""The 1 kHz FRI cycle engine: when the robot measures, and when it steps.

A state machine driven by ``tick(now)`` with an injected clock (dm_control's
viewer runtime is the pattern), so tests drive it on a fake clock and both
transports drive the same engine.  It runs one episode of FRI cycles of a
``participant`` (the robot node), which does the work:

    participant.open_cycle()              measure, publish robot/state and robot/contact
    participant.answered(names, seq)      have these participants answered cycle seq?
    participant.close_cycle(stop_on)      apply the answers, step the physics;
                                          returns why the episode ends, or None

Clocks:

- ``lockstep``: a cycle is opened, then closed once every participant in
  ``answers_from`` has answered it (``phase`` only on every tenth cycle, the
  estimator's 100 Hz), or when ``answer_timeout`` has passed (a missed answer).
  Simulated time advances at the pace of the slowest participant; the same seed
  gives the same run.  ``tick(now, quiescent=True)`` says that nothing more can
  arrive (the in-process transport has delivered everything): a cycle still
  waiting then closes at once, with a missed answer.
- ``realtime``: cycle k opens at its deadline t0 + k * period (the KRC sends its
  measurement at the start of the cycle) and closes as soon as its answers have
  arrived, or at the next deadline when they have not (FRI then counts a miss and
  bridges with the last command).  So an answer has the whole cycle, less the
  time to measure, instead of what is left after stepping the physics.  After an
  overrun the engine skips to the next future deadline rather than bursting to
  catch up (one stall must not snowball).

``tick`` returns the time it next needs to be called at (a deadline, or an
answer timeout), or None when the episode is over; a transport also calls it
whenever an answer arrives.
"""

from __future__ import annotations

from dataclasses import dataclass

from services.runtime.loop import LoopTiming
from services.runtime.messages import estimator_instant
from services.runtime.roles import PARTICIPANTS as ROLE_OF_PARTICIPANT

CLOCKS = ("lockstep", "realtime")
PARTICIPANTS = tuple(ROLE_OF_PARTICIPANT)
LOCKSTEP_GIVE_UP = 2  # consecutive timed-out cycles before a lockstep episode ends as unanswered
# the sensor's record of a cycle: beside the commander's answer, a lockstep cycle waits for it
# to keep the sensor in step with the arm (services.run.episode), not for an answer the arm
# needs.  One that lets a cycle time out there (a sensor stopped, its stream cut, its link
# fooled by a foreign peer) is not waited for again until it records a cycle, and its silence
# does not end the episode: what the missing wrench means is the commander's to say (a stale
# estimate holds the arm).  Elsewhere (a demonstration, whose recording is what it is for; a
# settle) a silent sensor ends the episode as anyone's silence does
IN_STEP_ONLY = ("ft",)


@dataclass(frozen=True)
class EpisodePlan:
    """What one run of cycles is: ``max_cycles`` at most, exactly ``cycles`` for a
    settle, ending early on ``stop_on`` ('teacher_done', 'goal_reached' or None)."""

    max_cycles: int
    answers_from: tuple = ()
    stop_on: str | None = None
    cycles: int | None = None  # settle: the number of cycles to run

    def __post_init__(self):
        unknown = set(self.answers_from) - set(PARTICIPANTS)
        if unknown:
            raise ValueError(f"answers_from: unknown participants {sorted(unknown)} (known: {list(PARTICIPANTS)})")
        if self.stop_on not in (None, "teacher_done", "goal_reached"):
            raise ValueError(f"stop_on must be teacher_done, goal_reached or null, got {self.stop_on!r}")
        if not (isinstance(self.max_cycles, int) and self.max_cycles >= 1):
            raise ValueError(f"max_cycles must be an integer >= 1, got {self.max_cycles!r}")

    @property
    def default_reason(self) -> str:
        # with nothing to stop on (a hold run), reaching max_cycles is the plan, not a timeout
        return "timeout" if self.stop_on or self.cycles is not None else "elapsed"


class CycleEngine:
    def __init__(self, participant, plan: EpisodePlan, clock, *, mode: str, cycle_ns: int,
                 answer_timeout_ns: int = 5_000_000_000, stall_every_cycles: int = 0, stall_s: float = 0.0):
        if mode not in ("lockstep", "realtime"):
            raise ValueError(f"clock must be lockstep or realtime, got {mode!r}")
        self.p = participant
        self.plan = plan
        self.clock = clock
        self.lockstep = mode == "lockstep"
        self.period = int(cycle_ns)
        self.answer_timeout = int(answer_timeout_ns)
        self.stall_every = int(stall_every_cycles)
        self.stall_s = float(stall_s)
        self.timing = LoopTiming(self.period)
        self.k = 0  # cycles closed
        self.missed_answers = 0
        self.reason = plan.default_reason
        self.done = False
        self._open_seq = None
        self._open_stamp = 0
        self._opened_at = 0
        self._work_start = 0
        self._deadline = None  # realtime: the start of the next cycle
        self._idle_since = None
        self._timeouts = 0  # lockstep: consecutive cycles closed at the answer timeout
        self._unwaited: set = set()  # IN_STEP_ONLY participants that timed out and have not recorded since
        self._in_step_only = IN_STEP_ONLY if "command" in plan.answers_from else ()
        self._wait_for_all_but(self._unwaited)
        self._need = self._most

    # ------------------------------------------------------------- state

    @property
    def open_seq(self) -> int | None:
        return self._open_seq

    def awaiting(self) -> bool:
        """A cycle is open and not all of its answers have come."""
        return self._open_seq is not None and not self._answered()

    def _needed(self) -> list:
        return self._need

    def _answered(self) -> bool:
        return self.p.answered(self._needed(), self._open_seq)

    # ------------------------------------------------------------ driving

    def tick(self, now: int, quiescent: bool = False) -> int | None:
        if self.done:
            return None
        return self._tick_lockstep(now, quiescent) if self.lockstep else self._tick_realtime(now)

    def stop(self, reason: str = "stopped") -> None:
        """End the episode now; an open cycle is closed, not left measured but unapplied."""
        if self.done:
            return
        if self._open_seq is not None:
            if self.lockstep and not self._answered():
                self.missed_answers += 1
            self._close(None)
        self.reason = reason
        self.done = True

    def _tick_lockstep(self, now: int, quiescent: bool) -> int | None:
        if self._open_seq is not None:
            silent = []
            if not self._answered():
                if not quiescent and now - self._opened_at < self.answer_timeout:
                    return self._opened_at + self.answer_timeout
                self.missed_answers += 1
                if not quiescent:
                    silent = [w for w in self._needed() if not self.p.answered([w], self._open_seq)]
            if silent or self._unwaited:
                silent = self._keep_in_step(silent)
            self._timeouts = self._timeouts + 1 if silent else 0
            self.p.sections.add("wait", now - self._opened_at)
            self._close(self.plan.stop_on)
            if self._timeouts >= LOCKSTEP_GIVE_UP and not self.done:
                self.reason, self.done = "unanswered:" + ",".join(silent), True
            self.timing.record(0, self.clock.now_ns() - self._work_start, missed=False)
            if self._finished():
                return None
        self._work_start = self.clock.now_ns()
        self._open()
        self._opened_at = self.clock.now_ns()
        return self._opened_at + self.answer_timeout

    def _keep_in_step(self, silent: list) -> list:
        """``IN_STEP_ONLY`` (beside the commander): one silent at this timeout is no longer waited
        for, one that recorded this cycle is waited for again.  The participants whose silence counts."""
        back = {w for w in self._unwaited if self.p.answered([w], self._open_seq)}
        gone = {w for w in silent if w in self._in_step_only}
        if back or gone:
            self._unwaited = (self._unwaited - back) | gone
            self._wait_for_all_but(self._unwaited)
        return [w for w in silent if w not in self._in_step_only]

    def _wait_for_all_but(self, unwaited) -> None:
        """What a cycle waits for: the plan's answers but ``unwaited``, the estimator's only
        at its instants (``_open`` picks one of the two)."""
        self._every = [w for w in self.plan.answers_from if w not in unwaited]
        self._most = [w for w in self._every if w != "phase"]

    def _tick_realtime(self, now: int) -> int | None:
        if self._deadline is None:
            self._deadline = now
        if self._open_seq is not None and self._answered():
            # the answer is here: step now, measure again at the next deadline
            self._close(self.plan.stop_on)
            if self._finished():
                return None
            self._idle_since = self.clock.now_ns()
        if now < self._deadline:
            return self._deadline
        deadline = self._deadline
        if self._idle_since is not None:
            self.p.sections.add("wait", now - self._idle_since)
        if self._open_seq is not None:
            self._close(self.plan.stop_on)  # unanswered: FRI counts the miss and bridges
            if self._finished():
                return None
        if self.stall_every and self.k > 0 and self.k % self.stall_every == 0:
            self.clock.sleep(self.stall_s)  # injected fault: the loop stalls
        self._open()
        end = self.clock.now_ns()
        self.timing.record(now - deadline, end - now, missed=end > deadline + self.period)
        self._idle_since = end
        nxt = deadline + self.period
        if end >= nxt:
            nxt += (end - deadline) // self.period * self.period  # skip the periods already lost
        self._deadline = nxt
        return nxt

    def _open(self) -> None:
        self.p.sections.cycles += 1
        self._open_seq, self._open_stamp = self.p.open_cycle()
        # the answers this cycle waits for: the estimator's only at its instants
        self._need = self._every if estimator_instant(self._open_stamp) else self._most

    def _close(self, stop_on) -> None:
        why = self.p.close_cycle(stop_on)
        self._open_seq = None
        self.k += 1
        if why is not None:
            self.reason = why
            self.done = True

    def _finished(self) -> bool:
        if not self.done and self.plan.cycles is not None and self.k >= self.plan.cycles:
            self.reason, self.done = "settled", True
        elif not self.done and self.k >= self.plan.max_cycles:
            self.done = True  # with the plan's default reason
        return self.done
