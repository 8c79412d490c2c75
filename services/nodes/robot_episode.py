"""The robot's judge of one run of cycles (an episode, or a settle): what it accumulates
(the peak contact force, the answers' and the closed loop's latency, the FRI link's
state changes, the commander's first hold), when it ends (the teacher is done, the goal
is reached, the commander has held the arm for ``HOLD_WATCH_S``, the KRC stopped for
safety) and its summary, what ``robot/episode`` carries."""

from __future__ import annotations

import math

import numpy as np

from robot_sim.cycle import FRI_RATE_HZ
from robot_sim.krc.law import SafetyReason
from robot_sim.krc.packets import FriState
from services.runtime.loop import Sections
from services.runtime.messages import HOLD_WATCH_S
from services.runtime.timing import Histogram

HOLD_WATCH_CYCLES = int(HOLD_WATCH_S * FRI_RATE_HZ)
# per-cycle sections (episode summary, loop.sections): waiting for the deadline or the
# answers, handing the answers to the FRI link, the physics step (KRC law + MuJoCo +
# sensing), measuring (FRI packet, labels), encoding, publishing
SECTIONS = ("wait", "answers", "step", "measure", "encode", "publish")
_SENT_KEPT = 1000  # cycles whose send time is kept: the closed loop spans a few


class EpisodeJudge:
    """One run of cycles, from its first cycle (``first_seq``) on.  ``fri0``: the link's
    statistics when it began (the link counts over its whole session: the summary reports
    this episode's share)."""

    def __init__(self, first_seq: int, fri0, wall0_ns: int, cycle_ns: int):
        self.first_seq = first_seq
        self.fri0 = fri0
        self.wall0_ns = wall0_ns
        self.cycle_ns = cycle_ns
        self.k = 0  # cycles closed
        self.peak = 0.0
        self.answer = Histogram()
        self.closed_loop = Histogram()
        self.sent: dict[int, int] = {}  # seq -> when its measurement was published
        self.last_estimate = -1
        self.goal_at = -1.0
        self.hold = None  # the commander's first hold, and what the arm did while held
        self.hold_run = 0  # cycles the current hold has lasted
        self.hold_x0 = None  # the tcp where the current hold began
        self.run = 0
        self.miss_run = 0
        self.cmd_left = 0  # CMD -> MON (the link's quality fell below OK)
        self.cmd_entered = 0  # MON -> CMD
        self.cmd_cycles = 0  # cycles that ended in command mode
        self.states: list = []  # the link's state changes (seq, state, quality), when tracked
        self.refusals: list = []  # first commands the KRC refused (seq, at_s, reason)
        self.safety_stop = None  # served: the KRC's safety stop (seq, at_s, reason)
        self.fri_state = fri0.state  # the link keeps its state from one episode into the next
        self.sections = Sections(*SECTIONS)

    def at_s(self, k: int | None = None) -> float:
        """Episode time of cycle ``k`` (default: the cycles closed so far), s."""
        return (self.k if k is None else k) * self.cycle_ns / 1e9

    # ------------------------------------------------------------- during a cycle

    def measured(self, seq: int, sent_ns: int, contact_force: float) -> None:
        """Cycle ``seq``'s measurement went out at ``sent_ns`` with this contact force."""
        if contact_force > self.peak:
            self.peak = contact_force
        self.sent[seq] = sent_ns
        if len(self.sent) > 2 * _SENT_KEPT:
            for old in [k for k in self.sent if k < seq - _SENT_KEPT]:
                del self.sent[old]

    def estimate_used(self, estimate_seq: int, arrived_ns: int) -> None:
        """A command that used the estimate of cycle ``estimate_seq`` arrived: the closed loop
        (measurement -> sensor -> estimator -> commander -> here), once per estimate."""
        if estimate_seq > self.last_estimate and estimate_seq in self.sent:
            self.closed_loop.add(arrived_ns - self.sent[estimate_seq])
            self.last_estimate = estimate_seq

    def goal_reached(self) -> None:
        if self.goal_at < 0:
            self.goal_at = self.at_s()

    # ------------------------------------------------------------- after the step

    def judge(self, cell, outcome, seq: int, *, kind: str, stop_on, teacher_done: bool, goal_reached: bool,
              hold, estimate_seq: int, track_states: bool) -> str | None:
        """Cycle ``seq`` has stepped with ``outcome``: why the episode ends, or None.
        ``hold``: why this cycle's command holds the arm ('' it does not; None: no command)."""
        self.k += 1
        self._count_states(outcome, seq, track_states)
        fri = cell.fri
        if cell.first_command_refused:
            self.refusals.append(dict(seq=seq, at_s=self.at_s(), reason=cell.first_command_refused))
            cell.first_command_refused = ""
        if kind == "reproduction" and fri.state == FriState.MON and not fri.command_requested:
            # as the KRL program of a lab set-up does: after a fall-back to monitor
            # mode, ask for command mode again (entered once the link is PERFECT again)
            fri.request_command_mode()
        for flag, name in ((teacher_done, "teacher_done"), (goal_reached, "goal_reached")):
            if flag and stop_on == name:
                return name
        if hold:
            if self._watch_hold(cell, seq, hold, estimate_seq):
                return f"hold:{self.hold['reason']}"
        elif hold is not None:
            self.hold_run = 0
        if cell.krc.safety != 0:
            reason = SafetyReason(cell.krc.safety).name.lower()
            if kind != "served":
                return f"safety:{reason}"
            if self.safety_stop is None:
                # a lab's remote is served on: the KRC has dropped it to monitor mode, holds the
                # arm and reports the error in the measurement (RobotCell.remote_checks)
                self.safety_stop = dict(seq=seq, at_s=self.at_s(), reason=reason)
        return None

    def _count_states(self, outcome, seq: int, track_states: bool) -> None:
        if outcome.state != self.fri_state:
            if outcome.state == FriState.CMD:
                self.cmd_entered += 1
            elif self.fri_state == FriState.CMD:
                self.cmd_left += 1
            self.fri_state = outcome.state
        if outcome.state == FriState.CMD:
            self.cmd_cycles += 1
        if track_states and (not self.states or self.states[-1][1:] != (int(outcome.state), int(outcome.quality))):
            self.states.append((seq, int(outcome.state), int(outcome.quality)))
        self.run = 0 if outcome.answered else self.run + 1
        self.miss_run = max(self.miss_run, self.run)

    def _watch_hold(self, cell, seq: int, reason: str, estimate_seq: int) -> bool:
        """The commander holds the arm this cycle: what the arm does meanwhile (how far the
        tcp goes, how hard it presses); True once the hold has lasted HOLD_WATCH_S."""
        if self.hold is None:
            self.hold = dict(reason=reason, seq=seq, at_s=self.at_s(self.k - 1), estimate_seq=estimate_seq,
                             cycles=0, max_displacement_m=0.0, peak_contact_force=0.0)
        if self.hold_run == 0:
            self.hold_x0 = cell.sim.tcp_position()
        self.hold_run += 1
        h = self.hold
        h["cycles"] += 1
        h["max_displacement_m"] = max(h["max_displacement_m"],
                                      float(np.linalg.norm(cell.sim.tcp_position() - self.hold_x0)))
        h["peak_contact_force"] = max(h["peak_contact_force"], math.hypot(*cell.contact_force[:3]))
        return self.hold_run >= HOLD_WATCH_CYCLES

    # ------------------------------------------------------------- the summary

    def summary(self, engine, cell, *, episode: int, kind: str, now_ns: int, clock: str, sched_fifo,
                wire: dict | None = None) -> dict:
        """What robot/episode carries for this run of cycles."""
        stats = cell.fri.statistics()
        fri0 = self.fri0
        return dict(
            seq=cell.fri.seq, stamp_ns=cell.t_ns, sent_ns=now_ns, episode=episode, kind=kind,
            reason=engine.reason, first_seq=self.first_seq, last_seq=cell.fri.seq,
            sim_seconds=engine.k * cell.cycle_ns / 1e9, wall_seconds=(now_ns - self.wall0_ns) / 1e9,
            final_position=cell.sim.tcp_position(), peak_contact_force=self.peak, safety=int(cell.krc.safety),
            missed_answers=engine.missed_answers, goal_reached_at_s=self.goal_at,
            **({"hold": dict(self.hold)} if self.hold is not None else {}),
            fri={"answered": stats.answered - fri0.answered, "missed": stats.missed - fri0.missed,
                 "late": stats.late - fri0.late, "corrupt": stats.corrupt - fri0.corrupt,
                 "duplicate": stats.duplicate - fri0.duplicate, "longest_miss_run": self.miss_run,
                 "command_mode_entered": self.cmd_entered, "command_mode_left": self.cmd_left,
                 "state": int(stats.state), "quality": int(stats.quality)},
            loop=dict(engine.timing.summary(), clock=clock, sched_fifo=sched_fifo,
                      answer_latency=self.answer.to_dict(), closed_loop_latency=self.closed_loop.to_dict(),
                      sections=self.sections.summary(), wall_start_ns=self.wall0_ns, wall_end_ns=now_ns),
            **({"wire": wire} if wire is not None else {}),
        )
