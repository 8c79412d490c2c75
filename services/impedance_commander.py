"""impedance_commander: per-phase Cartesian impedance from the learned model, 1 kHz.

Answers every FRI measurement (``robot/state``) with a command echoing its
seq (``robot/command``).  The phase is the estimator's most likely phase
(``estimator/phase``, 100 Hz; in lockstep the commander waits for the
estimate of the same cycle every tenth cycle).

On the realtime clock only answers that can still count are sent: the
commander takes the newest measurement that has arrived (an older one's cycle
closed when the robot sent the next; ``Service.subscribe(latest=True)``) and
leaves unanswered one that is already a cycle old (``stale`` in its status):
its answer could only reach the KRC late, which FRI counts as a miss all the
same, and computing it would delay the answer to the cycle that is still open.
The law then integrates over the cycles that passed (``dt``).  Lockstep
answers every measurement.

The impedance of each phase is the one derived from its demonstration data
(``etar.impedance``: direction d, compliant axes, K = R V R^T, mean contact
force; stored in the model file's metadata).  The commander moves a reference
point along d at the phase's demonstrated speed (never more than ``lead``
ahead of the tool, so a blocked tool does not wind the spring up), and
commands

    F = K (x_ref - x) + F_ff - D v,   F_ff = -(mean contact force on the compliant axes)

i.e. stiff along d and the other non-compliant axes, soft along the compliant
axes, pressing into the surfaces as the teacher did.  FRI's own stiffness is
diagonal in the tcp frame, so the full K is realised through addTcpFT (the
superposed wrench, thesis eq. 79) with the KRC's translational stiffness at
zero; the KRC's rotational stiffness holds the start orientation.  At the goal
(the demonstrations' mean end point) the reference stops and the commander
reports ``goal_reached``.

With a pose state the model also holds each phase's mean angular velocity and
the demonstrations' mean final turn (``goal_rotation``).  A turning phase turns
the setpoint orientation at its rate, never more than ``ROT_LEAD`` ahead of the
tool and never past the goal's turn, through the KRC's rotational stiffness;
the goal then also needs the turn.  A phase done in place (``in_place`` in the
model: the coupler's coupling, press and turn) has no direction to follow: its
reference goes, stiffly, to where the demonstrations did it, and there the
phase's law presses along its compliant axis as the teacher did.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from etar import ETAR
from etar.impedance import IN_PLACE_SPEED
from robot_sim.cell import standard_to_fri
from services.runtime.loop import Sections
from services.runtime.messages import ROBOT_COMMAND
from services.runtime.timing import Histogram
from services.runtime.service import Service, now_ns
from services.runtime.session import ZenohOptions, add_zenoh_arguments, zenoh_options

DT = 0.001
CYCLE_NS = 1_000_000  # the FRI cycle: an answer later than this after its measurement is late
PERIOD_NS = 10_000_000  # the estimator's period (simulated time)
HOLD_STIFFNESS = 2000.0
ROT_STIFFNESS = 150.0
EFFECTIVE_MASS = 2.0  # kg, for the damping ratio of the commanded impedance
ESTIMATE_WAIT_S = 2.0  # lockstep: how long to wait for a cycle's estimate before going on without it
# rad: the setpoint orientation turns at most this far ahead of the tool, 15 Nm at
# ROT_STIFFNESS: enough to turn against a seal's friction, bounded if the tool is stuck
ROT_LEAD = 0.1
ROT_TOLERANCE = 0.1  # rad: how close to the goal's turn counts as there
TURNING_RATE = 1e-3  # rad/s: a phase with a slower mean angular velocity does not turn
PLACE_SPEED = 0.02  # m/s: how fast a phase done in place moves its reference to where it was demonstrated
_CART_STIFFNESS = [0.0, 0.0, 0.0] + [ROT_STIFFNESS] * 3
_CART_DAMPING = [0.7] * 6


@dataclass(frozen=True)
class CommanderConfig:
    run_id: str
    zenoh: ZenohOptions
    sched_fifo: int = 0  # SCHED_FIFO priority, 0: none
    cpus: tuple = ()  # CPU affinity of the whole process, (): any
    clock: str = "lockstep"
    model: str | None = None
    # m: the stiff axis pushes a blocked tool with at most K lead: 10 N at 2000 N/m, the
    # order of the demonstrated contact forces.  With 2 cm (40 N) the free-motion law slid
    # the tool down the plate faster than any demonstration, and the estimator, which
    # judges phases by their dynamics, flickered between free motion and plate.
    lead: float = 0.005
    damping_ratio: float = 0.7
    goal_tolerance: float = 0.01
    stall_every_s: float = 0.0  # fault injection: stall before answering, every N s of simulated time
    stall_ms: float = 0.0


@dataclass(frozen=True)
class PhaseLaw:
    """One phase's impedance as arrays, prepared once from the model file."""

    direction: np.ndarray  # (3,)
    stiffness: np.ndarray  # (3, 3) K = R V R^T
    damping: np.ndarray  # (3, 3)
    feedforward: np.ndarray  # (3,) -(mean contact force on the compliant axes)
    speed: float  # m/s along the direction
    angular_velocity: np.ndarray  # (3,) rad/s, axes of the episode's first orientation
    in_place: bool  # demonstrated without going anywhere: go to where it happened and stay
    place: np.ndarray | None  # (3,) the demonstrations' mean position in this phase
    aim: np.ndarray | None  # (3,) free motion into a phase done in place: head for its place


class ImpedanceLaw:
    """The per-phase law, free of messaging (tested on its own)."""

    def __init__(self, impedances: list, goal: np.ndarray | None, *, lead=0.005, damping_ratio=0.7,
                 goal_tolerance=0.01, goal_rotation: np.ndarray | None = None, rotation_tolerance=ROT_TOLERANCE):
        self.zeta = damping_ratio
        self.phases = [None if imp is None else self._prepare(imp, impedances) for imp in impedances]
        self.hold_stiffness = HOLD_STIFFNESS * np.eye(3)
        self.hold_damping = self._damping(self.hold_stiffness)
        self.goal = None if goal is None else np.asarray(goal, dtype=np.float64)
        # the goal's turn counts only if the demonstrations turned noticeably
        self.goal_rotation = None
        if goal_rotation is not None and np.linalg.norm(goal_rotation) > rotation_tolerance:
            self.goal_rotation = np.asarray(goal_rotation, dtype=np.float64)
            self._goal_turn_T = pin.exp3(self.goal_rotation).T
        self.lead = lead
        self.tol = goal_tolerance
        self.rot_tol = rotation_tolerance
        self.reset()

    def _prepare(self, imp: dict, impedances: list) -> PhaseLaw:
        K = np.asarray(imp["stiffness"], dtype=np.float64)
        mean_force = np.asarray(imp["mean_force"], dtype=np.float64)
        F_ff = np.zeros(3)
        for a in np.asarray(imp["compliant_axes"], dtype=np.float64).reshape(-1, 3):
            F_ff -= (mean_force @ a) * a
        omega = np.asarray(imp.get("angular_velocity", (0.0, 0.0, 0.0)), dtype=np.float64)
        if np.linalg.norm(omega) < TURNING_RATE:
            omega = np.zeros(3)
        demonstrated = float(imp["mean_speed"])
        place = imp.get("mean_position")
        # model files from before in_place was learned: judge by the speed along d
        in_place = bool(imp.get("in_place", demonstrated < IN_PLACE_SPEED))
        # free motion whose successor is done in place (the coupler's approach) heads for
        # that place: a fixed direction from another start would miss a 36 mm socket
        aim = None
        nxt = imp.get("successor")
        if not in_place and imp["n_compliant"] == 0 and nxt is not None and 0 <= nxt < len(impedances):
            follow = impedances[nxt]
            if follow is not None and follow.get("in_place") and follow.get("mean_position") is not None:
                aim = np.asarray(follow["mean_position"], dtype=np.float64)
        return PhaseLaw(np.asarray(imp["direction"], dtype=np.float64), K, self._damping(K), F_ff,
                        max(demonstrated, 0.01), omega, in_place,
                        None if place is None else np.asarray(place, dtype=np.float64), aim)

    def reset(self):
        self.phase = None
        self.ref = None
        self.R_hold = None
        self.turn_ref = np.zeros(3)  # setpoint orientation: R_hold exp(turn_ref); kept across phases
        self.at_place = False  # a phase done in place: its tool has arrived where it was demonstrated
        self.prev_x = None
        self.v = np.zeros(3)
        self.goal_reached = False

    def _setpoint_rotation(self) -> np.ndarray:
        if not self.turn_ref.any():
            return self.R_hold
        return self.R_hold @ pin.exp3(self.turn_ref)

    def _turn(self, law: PhaseLaw, turned: np.ndarray, dt: float) -> None:
        """Advance the setpoint's turn at the phase's rate: at most ROT_LEAD ahead of
        the tool's ``turned`` (rotation vector from R_hold), never past the goal's."""
        w = law.angular_velocity
        self.turn_ref = self.turn_ref + w * dt
        ahead = self.turn_ref - turned
        if np.linalg.norm(ahead) > ROT_LEAD:
            self.turn_ref = turned + ahead * (ROT_LEAD / np.linalg.norm(ahead))
        if self.goal_rotation is not None:
            axis = w / np.linalg.norm(w)
            beyond = (self.turn_ref - self.goal_rotation) @ axis
            if beyond > 0.0:
                self.turn_ref = self.turn_ref - beyond * axis

    def _turned_enough(self, turned: np.ndarray) -> bool:
        if self.goal_rotation is None:
            return True
        return bool(np.linalg.norm(pin.log3(self._goal_turn_T @ pin.exp3(turned))) < self.rot_tol)

    def step(self, x: np.ndarray, R: np.ndarray, phase: int | None, dt: float = DT) -> tuple[np.ndarray, np.ndarray]:
        """(force in base axes (3,), setpoint rotation) for this cycle; ``dt``: time since
        the previous step (more than one cycle when realtime left measurements unanswered)."""
        if self.R_hold is None:
            self.R_hold = R.copy()
        if self.prev_x is not None:
            # a light low-pass on the finite-difference velocity (1 ms steps)
            self.v = 0.7 * self.v + 0.3 * (x - self.prev_x) / dt
        self.prev_x = x.copy()
        law = self.phases[phase] if phase is not None and 0 <= phase < len(self.phases) else None
        if phase != self.phase:
            # a new phase starts its reference at the tool, already half a lead
            # ahead along its direction: a flickering estimate must not stall the motion
            self.phase = phase
            self.at_place = False
            moving = law is not None and not law.in_place
            self.ref = x + law.direction * 0.5 * self.lead if moving else x.copy()
        if self.goal_reached or law is None:
            if self.ref is None:
                self.ref = x.copy()
            return self.hold_stiffness @ (self.ref - x) - self.hold_damping @ self.v, self._setpoint_rotation()
        d = law.direction
        if law.aim is not None and np.linalg.norm(law.aim - x) > self.lead:
            # free space: K is isotropic, so turning d changes nothing else; the
            # reference keeps only its lead along the new d
            d = (law.aim - x) / np.linalg.norm(law.aim - x)
            self.ref = x + max((self.ref - x) @ d, 0.0) * d
        if not law.in_place:
            self.ref = self.ref + d * law.speed * dt
            ahead = (self.ref - x) @ d
            if ahead > self.lead:
                self.ref -= d * (ahead - self.lead)
        elif law.place is not None:
            # towards where the phase was demonstrated, at most a lead ahead of the tool
            to_place = law.place - self.ref
            step = min(np.linalg.norm(to_place), PLACE_SPEED * dt)
            if step > 0.0:
                self.ref = self.ref + to_place * (step / np.linalg.norm(to_place))
            ahead = self.ref - x
            if np.linalg.norm(ahead) > self.lead:
                self.ref = x + ahead * (self.lead / np.linalg.norm(ahead))
        going = law.in_place and law.place is not None and not self.at_place
        if going:
            self.at_place = bool(np.linalg.norm(law.place - self.ref) < 1e-6
                                 and np.linalg.norm(law.place - x) < self.lead)
            going = not self.at_place
        if going:
            # on the way to the place: stiff and damped on every axis, no push, so the
            # tool arrives at the reference's pace (dropping off a rim onto the floor
            # under the phase's push along a soft axis hit it with 70 N); the phase's own
            # law, with its push, starts there
            F = self.hold_stiffness @ (self.ref - x) - self.hold_damping @ self.v
        else:
            F = law.stiffness @ (self.ref - x) + law.feedforward - law.damping @ self.v
        turned = None
        if law.angular_velocity.any() or self.goal_rotation is not None:
            turned = pin.log3(self.R_hold.T @ R)
            if law.angular_velocity.any():
                self._turn(law, turned, dt)
        if self.goal is not None and phase == len(self.phases) - 1:
            past = not law.in_place and (x - self.goal) @ d >= 0.0
            lateral = np.linalg.norm((x - self.goal) - ((x - self.goal) @ d) * d)
            there = np.linalg.norm(x - self.goal) < self.tol or (past and lateral < 3 * self.tol)
            if there and (turned is None or self._turned_enough(turned)):
                self.goal_reached = True
                self.ref = x.copy()
        return F, self._setpoint_rotation()

    def _damping(self, K):
        w, V = np.linalg.eigh(0.5 * (K + K.T))
        c = 2.0 * self.zeta * np.sqrt(np.maximum(w, 0.0) * EFFECTIVE_MASS)
        return V @ np.diag(c) @ V.T


class CommanderProcess:
    def __init__(self, config: CommanderConfig, svc: Service):
        self.config = config
        self.svc = svc
        self.law = None
        self.episode = -1
        self._lock = threading.Lock()
        self._pending: dict[int, dict] = {}
        self._phases: dict[int, int] = {}
        self._latest_phase = None
        self._latest_phase_seq = -1
        self._waiting_since = None
        self._last_answered_seq = None
        self.missing_estimates = 0
        self.stale = 0  # realtime: measurements left unanswered, already a cycle old when their turn came
        # where an answer's time goes, and receive -> published (the commander's share of
        # the FRI answer latency)
        self.sections = Sections("decode", "law", "encode", "publish")
        self.answer_time = Histogram()
        self._recv_ns = 0
        realtime = config.clock == "realtime"
        self._pub = svc.publisher("robot/command", drop_when_congested=realtime)
        self.model = ETAR.load(config.model) if config.model else None
        svc.subscribe("robot/state", self.on_state, latest=realtime)
        svc.subscribe("estimator/phase", self.on_phase, latest=realtime)

    def on_phase(self, msg, recv_ns, raw):
        with self._lock:
            if msg["episode"] != self.episode:
                return
            self._latest_phase = msg["phase"]
            self._latest_phase_seq = msg["seq"]
            if self.config.clock == "lockstep":  # realtime uses the latest estimate, whatever its cycle
                self._phases[msg["seq"]] = msg["phase"]
                self._drain()

    def on_state(self, msg, recv_ns, raw):
        with self._lock:
            # only the cycles of the reproduction this commander was reset for are
            # answered: answers to others (demonstrations, the rest while the
            # sensor is tared) would reach the FRI link at times that depend on
            # the machine, and lockstep runs must not
            if self.law is None or msg["episode"] != self.episode:
                return
            t = now_ns()
            if self.config.clock == "realtime" and t - msg["sent_ns"] >= CYCLE_NS:
                self.stale += 1  # its cycle is over: an answer now could only be late
                return
            self.sections.cycles += 1
            self.sections.add("decode", t - recv_ns)  # receive -> here: decoding and the lock
            self._recv_ns = recv_ns
            self._pending[msg["seq"]] = msg
            self._drain()

    def _drain(self, give_up: bool = False):
        lockstep = self.config.clock == "lockstep"
        for seq in sorted(self._pending):
            if lockstep and self._pending[seq]["stamp_ns"] % PERIOD_NS == 0 and seq not in self._phases:
                if not give_up:
                    self._waiting_since = self._waiting_since or time.monotonic()
                    return  # wait for this cycle's estimate
                # the estimate is not coming (the estimator skipped the sample): go on with the last one
                self.missing_estimates += 1
            self._waiting_since = None
            state = self._pending.pop(seq)
            phase = self._phases.pop(seq, None)
            if phase is not None:
                self._latest_phase = phase
                self._latest_phase_seq = seq
            self._answer(state)

    def _answer(self, state):
        c = self.config
        seq, last = state["seq"], self._last_answered_seq
        if c.stall_ms > 0 and c.stall_every_s > 0:
            # injected fault: the first answer of every stall_every_s of simulated time comes late
            # (the first one answered: realtime may have left the cycle on the mark unanswered)
            every, stamp = int(c.stall_every_s * 1e9), state["stamp_ns"]
            if stamp % every == 0 or (last is not None and stamp // every > (stamp - (seq - last) * CYCLE_NS) // every):
                time.sleep(c.stall_ms / 1e3)
        t0 = now_ns()
        m = np.asarray(state["msr_cart_pos"]).reshape(3, 4)
        R, x = m[:, :3], m[:, 3]
        cycles = seq - last if last is not None and 0 < seq - last <= 100 else 1
        self._last_answered_seq = seq
        F, R_set = self.law.step(x, R, self._latest_phase, cycles * DT)
        add = standard_to_fri(np.concatenate([R.T @ F, np.zeros(3)]))
        t1 = now_ns()
        raw = ROBOT_COMMAND.encode(
            seq=state["seq"], stamp_ns=state["stamp_ns"], sent_ns=t1,
            cart_pos=np.hstack([R_set, x[:, None]]).ravel(),
            cart_stiffness=_CART_STIFFNESS, cart_damping=_CART_DAMPING,
            add_tcp_ft=add, requested_mode=2, phase=-1 if self._latest_phase is None else int(self._latest_phase),
            estimate_seq=self._latest_phase_seq,
            goal_reached=bool(self.law.goal_reached), episode=state["episode"])
        t2 = now_ns()
        self._pub.put(raw)
        t3 = now_ns()
        sec = self.sections
        sec.add("law", t1 - t0)
        sec.add("encode", t2 - t1)
        sec.add("publish", t3 - t2)
        self.answer_time.add(t3 - self._recv_ns if self._recv_ns else 0)

    def reset(self, p: dict) -> None:
        with self._lock:
            if p.get("model"):
                self.model = ETAR.load(p["model"])
            if self.model is None:
                raise ValueError("no model: pass 'model' with reset or --model")
            imps = self.model.metadata.get("impedance")
            if not imps:
                raise ValueError("the model file has no per-phase impedance (metadata.impedance); "
                                 "learn it with etar learn or the runner")
            goal = p.get("goal")
            self.law = ImpedanceLaw(imps, goal, lead=self.config.lead, damping_ratio=self.config.damping_ratio,
                                    goal_tolerance=float(p.get("goal_tolerance", self.config.goal_tolerance)),
                                    goal_rotation=p.get("goal_rotation", self.model.metadata.get("goal_rotation")))
            self.episode = int(p["episode"])
            self._pending.clear()
            self._phases.clear()
            self._latest_phase = None
            self._latest_phase_seq = -1
            self._waiting_since = None
            self._last_answered_seq = None

    def _unstick(self) -> None:
        with self._lock:
            if self._waiting_since is not None and time.monotonic() - self._waiting_since > ESTIMATE_WAIT_S:
                self._drain(give_up=True)

    def serve(self) -> None:
        self.svc.serve({"reset": self.reset}, idle=self._unstick,
                       status=lambda: {"episode": self.episode, "missing_estimates": self.missing_estimates,
                                       "stale": self.stale,
                                       "sections": self.sections.summary(),
                                       "receive_to_answer": self.answer_time.summary()})


def main(config: CommanderConfig) -> int:
    with Service("impedance_commander", config.run_id, config.zenoh, sched_fifo=config.sched_fifo,
                 cpus=config.cpus) as svc:
        proc = CommanderProcess(config, svc)
        svc.log(f"ready: clock {config.clock}")
        proc.serve()
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="etar-impedance-commander", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-id", required=True)
    parser.add_argument("--clock", choices=("lockstep", "realtime"), default="lockstep")
    parser.add_argument("--model", help="learned model file with per-phase impedance; can also come with reset")
    parser.add_argument("--lead", type=float, default=0.005,
                        help="how far the reference may run ahead of the tool, m (default 0.005)")
    parser.add_argument("--damping-ratio", type=float, default=0.7)
    parser.add_argument("--stall-every", type=float, default=0.0,
                        help="fault injection: stall before answering every N s of simulated time")
    parser.add_argument("--stall-ms", type=float, default=0.0, help="fault injection: stall length, ms")
    add_zenoh_arguments(parser)
    return parser


def cli(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return main(CommanderConfig(run_id=args.run_id, zenoh=zenoh_options(args), clock=args.clock, model=args.model,
                                lead=args.lead, damping_ratio=args.damping_ratio, sched_fifo=args.sched_fifo,
                                cpus=args.cpus,
                                stall_every_s=args.stall_every, stall_ms=args.stall_ms))


if __name__ == "__main__":
    sys.exit(cli())
