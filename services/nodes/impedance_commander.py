"""The impedance_commander node: the learned task's reproduction policy, 1 kHz.

Answers every FRI measurement (``robot/state``) with a command echoing its seq
(``robot/command``).  The phase is the estimator's most likely phase
(``estimator/phase``, 100 Hz; in lockstep the commander waits for the estimate of
the same cycle every tenth cycle, and goes on with the last one if it does not
come: after 2 s over a network, at once in one process, where nothing more can
arrive).

The force comes from the learned task's reproduction policy (``etar.policy``).
FRI's own stiffness is diagonal in the tcp frame, so the full K = R V R^T is
realised through addTcpFT (the superposed wrench, thesis eq. 79) with the KRC's
translational stiffness at zero; the KRC's rotational stiffness holds (or turns)
the setpoint orientation.

A stale phase estimate is a fault, as in a real cell: when the newest estimate
is more than 50 cycles (five estimator periods, 50 ms) older than the
measurement being answered (the estimator is dead, hung or cut off, or it skips
every sample because the wrench stream stopped, saturated or went non-finite),
the commander holds the arm stiffly where it is (the policy's hold: 2000 N/m on
every axis, no feed-forward) and says why in every command (``hold``).  Following
the last phase on would drive the arm on a frozen belief (59-81 mm, up to 11 N,
before this hold existed).  In lockstep the hold lasts for the rest of the
episode: nothing is ever late there, so a stale estimate is one that will not
come.  On the realtime clock an estimate can be late and then come (a crowded
CPU): the hold lasts while the estimate is stale, and the policy resumes with
the next fresh one.  The robot ends the episode once a hold has lasted 1 s.  An
estimate that says its wrench could not be used (``input_fault``: the sensor
saturated or read non-finite) is a fault of the same kind, acted on at once: the
hold's reason is the estimate's.  An estimate taken after a missing sample
(``unconditioned: gap``) does not move the filter, so it does not count as fresh:
an estimator that misses every other sample anchors every one it takes, and its
belief is frozen while its estimates keep coming.

``--fri-listen HOST:PORT`` (``etar-bench run --wire udp``, realtime): the commander is
the KRC's FRI 1.0 remote over UDP, as a lab's control PC is.  The measurement datagrams
come to its socket; each is passed on to the rest of the run as ``robot/state`` (as the
lab's FRI component passed them on to its Orocos graph) and, during its reproduction,
answered with a command datagram to the address it came from.  What a ``robot/command``
says beyond FRI (the goal reached, a hold and its reason, the estimate used) goes on the
KRL channels (``robot_sim.krc.krl``'s testbench layout); ``robot/command`` is still published,
for the recording.

On the realtime clock only answers that can still count are sent: the commander
takes the newest measurement that has arrived (``latest``) and leaves unanswered
one that is already a cycle old (``stale`` in its status): its answer could only
reach the KRC late, which FRI counts as a miss all the same, and computing it
would delay the answer to the cycle that is still open.  The policy then
integrates over the cycles that passed (``dt``).  Lockstep answers every one.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

from etar.policy import LEAD, ReproductionPolicy
from etar.policy_kernel import compiled_policy
from etar.task import load_task
from robot_sim.wire.fri_udp import host_port
from services.runtime.bus import Node, Publication, Subscription
from services.runtime.config import check_stall, option
from services.runtime.loop import Sections
from robot_sim.cycle import FRI_CYCLE_NS
from services.runtime.messages import (ESTIMATOR_PHASE, ESTIMATOR_STRIDE, ROBOT_COMMAND, ROBOT_STATE,
                                       estimator_instant)
from services.runtime.timing import Histogram

ROT_STIFFNESS = 150.0
# five estimator periods: realtime estimates arrive up to a few cycles after their
# measurement, so only a silence far past that is a fault
STALE_ESTIMATE_CYCLES = 5 * ESTIMATOR_STRIDE
ESTIMATE_WAIT_S = 2.0  # lockstep over a network: how long to wait for a cycle's estimate before going on
CART_STIFFNESS = [0.0, 0.0, 0.0] + [ROT_STIFFNESS] * 3
CART_DAMPING = [0.7] * 6


@dataclass(frozen=True)
class CommanderConfig:
    model: str | None = option(None, "learned model file with per-phase impedance; can also come with reset",
                               metavar="FILE")
    lead: float = option(LEAD, "how far the reference may run ahead of the tool, m (> 0)", metavar="M")
    damping_ratio: float = option(0.7, "damping ratio of the commanded impedance, > 0 (1: critical)", metavar="RATIO")
    stall_every: float = option(0.0, "fault injection: stall before answering, every S seconds of simulated time, "
                                     ">= 0 (0: never)", metavar="S")
    stall_ms: float = option(0.0, "fault injection: how long each stall lasts, ms, >= 0", metavar="MS")
    fri_listen: str = option("", "be the KRC's FRI 1.0 remote over UDP on this address (measurements come here, "
                                 "commands go back; each measurement is passed on as robot/state); empty: "
                                 "robot/state and robot/command over the bus", metavar="HOST:PORT")

    def __post_init__(self):
        if not (math.isfinite(self.lead) and self.lead > 0):
            raise ValueError(f"lead must be > 0 m, got {self.lead!r}")
        # a ratio <= 0 commands no damping or energy into the arm: never an impedance to hold a task with
        if not (math.isfinite(self.damping_ratio) and self.damping_ratio > 0):
            raise ValueError(f"damping_ratio must be a finite number > 0, got {self.damping_ratio!r}")
        check_stall(self.stall_every, self.stall_ms)
        if self.fri_listen:
            host_port(self.fri_listen, "fri_listen", listen=True)


class ImpedanceCommanderNode(Node):
    name = "impedance_commander"

    def __init__(self, config: CommanderConfig, bus, clock, *, run_id: str = "", mode: str = "lockstep",
                 fri_remote=None, **_):
        super().__init__(bus, clock)
        self.config = config
        self.lockstep = mode == "lockstep"
        self.policy = None
        self.episode = -1
        self._lock = threading.Lock()
        self._pending: dict[int, dict] = {}
        self._phases: dict[int, dict] = {}  # lockstep: the estimates by cycle, until answered
        self._latest_phase = None
        self._latest_phase_seq = -1
        self._conditioned_seq = -1  # the newest estimate that moved the filter (not one anchored after a gap)
        self._input_fault = ""  # the newest estimate's: why its wrench could not be used
        self._waiting_since = None
        self._last_answered_seq = None
        self._first_seq = None
        self.hold = None  # the hold in force (reason, seq, estimate_seq); lockstep: until the next reset
        self.first_hold = None  # the episode's first
        self.holds = 0  # holds begun this episode
        self.missing_estimates = 0
        self.stale = 0  # realtime: measurements left unanswered, already a cycle old when their turn came
        # where an answer's time goes, and receive -> published (the commander's share of
        # the FRI answer latency)
        self.sections = Sections("decode", "law", "encode", "publish")
        self.answer_time = Histogram()
        self._recv_ns = 0
        self.task = load_task(config.model) if config.model else None
        self.publications = [Publication(ROBOT_COMMAND.topic, drop_when_congested=True)]
        self.subscriptions = [Subscription(ESTIMATOR_PHASE.topic, self.on_phase, latest=True)]
        self.fri = None
        if config.fri_listen:
            if self.lockstep:
                raise ValueError("fri_listen needs the realtime clock: the KRC sends on its own clock")
            self.publications.append(Publication(ROBOT_STATE.topic, drop_when_congested=True))
            if fri_remote is None:
                raise ValueError("fri_listen: the service process brings the FRI remote's socket "
                                 "(services.transport.lab)")
            self.fri = fri_remote(self._on_datagram)
        else:
            self.subscriptions.append(Subscription(ROBOT_STATE.topic, self.on_state, latest=True))

    @property
    def listening(self) -> bool:
        return self.policy is not None  # before its first reproduction it has nothing to answer

    def on_phase(self, msg, recv_ns, raw):
        with self._lock:
            self.deliver(self.take_phase(msg), self.bus.publish)

    # the answers (``robot/command`` as ``pack`` gives each) that a message or the end of waiting
    # lets the commander give; ``deliver`` hands them over.  Unlocked: the handlers hold the
    # lock; an engine that steps the nodes itself (services.transport.fused) calls them from its one thread

    def take_phase(self, msg) -> list:
        if msg["episode"] != self.episode:
            return []
        if self.lockstep:  # realtime uses the latest estimate, whatever its cycle
            self._phases[msg["seq"]] = msg
            return self._drain()
        self._take_estimate(msg)
        return []

    def _take_estimate(self, msg) -> None:
        self._latest_phase = msg["phase"]
        self._latest_phase_seq = msg["seq"]
        if msg.get("unconditioned") != "gap":
            self._conditioned_seq = msg["seq"]
        self._input_fault = msg.get("input_fault", "")

    def on_state(self, msg, recv_ns, raw):
        with self._lock:
            self.deliver(self.take_state(msg, recv_ns), self.bus.publish)

    def take_state(self, msg, recv_ns: int) -> list:
        # only the cycles of the reproduction this commander was reset for are
        # answered: answers to others (demonstrations, the rest while the
        # sensor is tared) would reach the FRI link at times that depend on
        # the machine, and lockstep runs must not
        if self.policy is None or msg["episode"] != self.episode:
            return []
        t = self.clock.now_ns()
        if not self.lockstep and t - msg["sent_ns"] >= FRI_CYCLE_NS:
            self.stale += 1  # its cycle is over: an answer now could only be late
            return []
        self.sections.cycles += 1
        self.sections.add("decode", t - recv_ns)  # receive -> here: decoding and the lock
        self._recv_ns = recv_ns
        self._pending[msg["seq"]] = msg
        return self._drain()

    def give_up(self) -> list:
        """Nothing more can arrive (one process): go on without the estimate waited for."""
        return self._drain(give_up=True) if self._waiting_since is not None else []

    def deliver(self, answers, hand_over) -> None:
        """Hand each answer over (``hand_over(topic, payload, message)``: the bus's publish),
        timed: the commander's share of the FRI answer latency ends here."""
        now, sec = self.clock.now_ns, self.sections
        for packed in answers:
            t = now()
            hand_over(ROBOT_COMMAND.topic, *packed)
            t3 = now()
            sec.add("publish", t3 - t)
            self.answer_time.add(t3 - self._recv_ns if self._recv_ns else 0)

    def _on_datagram(self, msg: dict, packed, recv_ns: int) -> None:
        """A measurement datagram (FriRemoteSocket's thread): passed on, and answered during
        this commander's reproduction."""
        with self._lock:
            if self.policy is not None and msg["episode"] == self.episode:
                self.sections.cycles += 1
                self.sections.add("decode", self.clock.now_ns() - recv_ns)
                self._recv_ns = recv_ns
                self.deliver([self._answer(msg)], self.bus.publish)
        # after the answer: the KRC waits for that, the estimator's copy does not
        self.bus.publish(ROBOT_STATE.topic, *packed)

    def _drain(self, give_up: bool = False) -> list:
        answers = []
        for seq in sorted(self._pending):
            # holding, it needs no estimate: it waits for none
            if self.lockstep and self.hold is None and estimator_instant(self._pending[seq]["stamp_ns"]) \
                    and seq not in self._phases:
                if not give_up:
                    if self._waiting_since is None:
                        self._waiting_since = self.clock.now_ns()
                    return answers  # wait for this cycle's estimate
                # the estimate is not coming (the estimator skipped the sample): go on with the last one
                self.missing_estimates += 1
            self._waiting_since = None
            state = self._pending.pop(seq)
            estimate = self._phases.pop(seq, None)
            if estimate is not None:
                self._take_estimate(estimate)
            answers.append(self._answer(state))
        return answers

    def _answer(self, state) -> tuple:
        c = self.config
        seq, last = state["seq"], self._last_answered_seq
        if c.stall_ms > 0 and c.stall_every > 0:
            # injected fault: the first answer of every stall_every of simulated time comes late
            # (the first one answered: realtime may have left the cycle on the mark unanswered)
            every, stamp = int(c.stall_every * 1e9), state["stamp_ns"]
            if stamp % every == 0 or (last is not None and stamp // every > (stamp - (seq - last) * FRI_CYCLE_NS) // every):
                self.clock.sleep(c.stall_ms / 1e3)
        now = self.clock.now_ns
        t0 = now()
        cycles = seq - last if last is not None and 0 < seq - last <= 100 else 1
        self._last_answered_seq = seq
        if self._first_seq is None:
            self._first_seq = seq
        if self.hold is None or not self.lockstep:
            fresh = self._conditioned_seq if self._conditioned_seq >= 0 else self._first_seq
            fault = "stale_estimate" if seq - fresh > STALE_ESTIMATE_CYCLES else self._input_fault
            if fault and self.hold is None:
                self.hold = dict(reason=fault, seq=seq, stamp_ns=state["stamp_ns"],
                                 estimate_seq=self._latest_phase_seq)
                self.holds += 1
                if self.first_hold is None:
                    self.first_hold = self.hold
            elif not fault:
                self.hold = None
        # the policy holds stiffly where the tool is when it knows no phase; it takes the KRC's
        # estimate of the external force (tcp axes, FRI order Fx Fy Fz first): it slides a
        # free-space phase along a surface it meets (etar.policy)
        policy = self.policy
        F, R_set, x = policy.tool_step(state["msr_cart_pos"], state["est_ext_tcp_ft"][:3],
                                       None if self.hold else self._latest_phase, cycles * FRI_CYCLE_NS / 1e9)
        # the force in tcp axes; FRI orders the torques Tz, Ty, Tx (all zero here)
        add = F.tolist() + [0.0, 0.0, 0.0]
        r, p = R_set.tolist(), x.tolist()
        cart = [*r[0], p[0], *r[1], p[1], *r[2], p[2]]  # the setpoint pose, 3x4 row-major [R | p]
        goal_reached, hold = bool(policy.goal_reached), self.hold["reason"] if self.hold else ""
        t1 = now()
        packed = ROBOT_COMMAND.pack(
            seq=seq, stamp_ns=state["stamp_ns"], sent_ns=t1, cart_pos=cart, cart_stiffness=CART_STIFFNESS,
            cart_damping=CART_DAMPING, add_tcp_ft=add, requested_mode=2,
            # the law that made this force: the estimate's, its successor's while that one is
            # blocked (etar.policy), or none (-1) while holding, at the goal included
            phase=-1 if policy.applied is None else int(policy.applied), estimate_seq=self._latest_phase_seq,
            goal_reached=goal_reached, hold=hold, episode=state["episode"])
        t2 = now()
        if self.fri is not None:
            # the answer to the KRC first; the bus's copy is for the recording
            self.fri.answer(state, cart, CART_STIFFNESS, CART_DAMPING, add, goal_reached=goal_reached, hold=hold,
                            estimate_seq=self._latest_phase_seq)
            self.sections.add("publish", now() - t2)
        sec = self.sections
        sec.add("law", t1 - t0)
        sec.add("encode", t2 - t1)
        return packed

    def handlers(self):
        return {"reset": self.reset}

    def reset(self, p: dict) -> None:
        task = load_task(p["model"]) if p.get("model") else self.task
        if task is None:
            raise ValueError("no model: pass 'model' with reset or --model")
        goal = p.get("goal", task.goal)
        goal_rotation = p.get("goal_rotation", task.goal_rotation)
        with self._lock:
            self.task = task
            # compiled where it can be (etar.policy_kernel: the same numbers, a tenth of the time)
            self.policy = compiled_policy(ReproductionPolicy(task.impedances, goal, lead=self.config.lead,
                                                             damping_ratio=self.config.damping_ratio,
                                                             goal_tolerance=float(p.get("goal_tolerance", 0.01)),
                                                             goal_rotation=goal_rotation))
            self.episode = int(p["episode"])
            self._pending.clear()
            self._phases.clear()
            self._latest_phase = None
            self._latest_phase_seq = -1
            self._conditioned_seq = -1
            self._input_fault = ""
            self._waiting_since = None
            self._last_answered_seq = None
            self._first_seq = None
            self.hold = self.first_hold = None
            self.holds = 0

    def idle(self, now_ns: int) -> None:
        with self._lock:
            if self._waiting_since is not None and now_ns - self._waiting_since > ESTIMATE_WAIT_S * 1e9:
                self.deliver(self._drain(give_up=True), self.bus.publish)

    def quiescent(self) -> None:
        with self._lock:
            self.deliver(self.give_up(), self.bus.publish)

    def status(self) -> dict:
        status = {"episode": self.episode, "missing_estimates": self.missing_estimates, "stale": self.stale,
                  "hold": self.first_hold, "holds": self.holds,
                  "sections": self.sections.summary(), "receive_to_answer": self.answer_time.summary()}
        if self.fri is not None:
            status["fri_udp"] = self.fri.status()
        return status

    def close(self) -> None:
        if self.fri is not None:
            self.fri.close()
