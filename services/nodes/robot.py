"""The robot node: the simulated LWR4+ behind its KRC/FRI link (``robot_sim.cell``).

Every FRI cycle (1 ms) it publishes ``robot/state`` (the FRI measurement) and
``robot/contact`` (the physics' truth for the F/T sensor and the labels); when
the cycle closes it applies the impedance commander's answer (``robot/command``,
echoing the measurement's seq) and the teacher's hand (``teacher/wrench``) and
steps the physics.  When cycles open and close is the cycle engine's business
(``services.runtime.cycle``): the node does the work of each.

In lockstep an answer is taken to arrive 0.1 ms after its measurement; in
realtime at its measured latency (receive time - publish time).

Control: ``reset`` (start, episode, kind), ``status``; the transports add
``settle``, ``run`` and ``stop``, which drive the engine (a request is checked
before its episode starts).

``--wire udp`` (realtime only): the KRC speaks FRI 1.0 over UDP instead
(``robot_sim.wire.fri_udp``): every cycle a 916-byte measurement datagram goes to the remote
at ``--fri-remote``, and the command datagram that answers it before the cycle ends is
applied; a KRL program (``robot_sim.krc.krl``, ``--krl``) starts and stops command mode as
the remote asks on the KRL channels.  The node goes on publishing ``robot/state`` and
``robot/contact``; both datagrams of every cycle also go out on ``fri/datagram``, as
bytes and decoded.  An episode of kind ``served`` holds the arm at its start in monitor
mode until the remote starts it (``etar-bench serve``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from robot_sim.cell import RobotCell
from robot_sim.cycle import FRI_CYCLE_NS
from robot_sim.krc.faults import LinkFaultSpec, LinkFaults
from robot_sim.krc.link import FriConfig
from robot_sim.krc.krl import KRL_CONVENTIONS
from robot_sim.wire.fri_datagrams import REMOTE_PORT
from robot_sim.wire.fri_udp import host_port
from robot_sim.world.labels import LABELERS
from robot_sim.world.teacher import DOWN
from robot_sim.world.tasks import TASK_WORLDS, Valley, WORLDS, physics_step, valley
from services.nodes.robot_episode import EpisodeJudge
from services.nodes.robot_inbox import AnswerInbox
from services.runtime.bus import Node, Publication, Subscription
from services.runtime.config import check_seed, check_stall, nested, option
from services.runtime.cycle import EpisodePlan
from services.runtime.fri_messages import deliver_command, measured_state, state_message
from services.runtime.messages import EPISODE_SUMMARY, FRI_DATAGRAM, ROBOT_CONTACT, ROBOT_STATE
from services.runtime.roles import PARTICIPANTS, ROLES

LOCKSTEP_LATENCY_NS = 100_000
ANSWER_TOPICS = {participant: ROLES[role].answer_topic for participant, role in PARTICIPANTS.items()}
WIRES = ("zenoh", "udp")
EPISODE_KINDS = ("demonstration", "reproduction", "served")


@dataclass(frozen=True)
class RobotConfig:
    world: str = option("valley", "task world", choices=TASK_WORLDS)
    seed: int = option(0, "seed of the cell (joint measurement noise), >= 0")
    answer_timeout: float = option(5.0, "lockstep: seconds to wait for a cycle's answers before counting a miss",
                                   metavar="S")
    stall_every: float = option(0.0, "fault injection: stall the loop every S seconds, >= 0 (0: never)", metavar="S")
    stall_ms: float = option(0.0, "fault injection: how long each stall lasts, ms, >= 0", metavar="MS")
    plate_friction: float = option(Valley.friction, "valley: sliding friction coefficient of the plates (> 0)",
                                   metavar="MU")
    physics_substeps: int = option(1, "physics steps per 1 ms FRI cycle, the KRC's law in each (more: the finer "
                                      "reference physics, slower; a divisor of 1 000 000)", metavar="N")
    # the FRI link's faults (--fri-packet-loss, ... --fri-faults-until-s): robot_sim.krc.faults.LinkFaultSpec
    fri: LinkFaultSpec = nested(LinkFaultSpec(), "fri_")
    wire: str = option("zenoh", "how the FRI remote talks to the KRC: zenoh (robot/command: the testbench's "
                                "commander) or udp (FRI 1.0 datagrams: a lab's remote; realtime only)",
                       choices=WIRES)
    fri_remote: str = option(f"127.0.0.1:{REMOTE_PORT}", "udp: the FRI remote's address, where the measurement "
                                                         "datagrams go", metavar="HOST:PORT")
    fri_bind: str = option("127.0.0.1:0", "udp: the KRC's own address (port 0: any free port)", metavar="HOST:PORT")
    fri_cycle_ms: int = option(1, "udp with a lab's KRL convention: the FRI cycle friOpen asks for, ms (1..100; the "
                                  "KRC's control runs every 1 ms physics step all the same)", metavar="MS")
    wire_topic: bool = option(True, "udp: publish every datagram that crosses the KRC's socket on fri/datagram, "
                                    "bytes and decoded (the recording of the wire: 2 messages and ~6 KB a cycle)")
    krl: str = option("frilibrary", "udp: the KRL program's start/stop convention on the KRL channels "
                                    "(frilibrary: the Stanford FRI Library's; lwr_hw: CentroEPiaggio's)",
                      choices=KRL_CONVENTIONS)

    def __post_init__(self):
        if self.world not in TASK_WORLDS:
            raise ValueError(f"world {self.world!r} unknown (known: {', '.join(TASK_WORLDS)})")
        if not (math.isfinite(self.answer_timeout) and self.answer_timeout > 0):  # inf: a lost answer hangs the run
            raise ValueError(f"answer_timeout must be a finite number of seconds > 0, got {self.answer_timeout!r}")
        check_seed(self.seed)
        check_stall(self.stall_every, self.stall_ms)
        if not (math.isfinite(self.plate_friction) and self.plate_friction > 0):
            raise ValueError(f"plate_friction must be a finite number > 0, got {self.plate_friction!r}")
        if self.wire not in WIRES:
            raise ValueError(f"wire must be one of {', '.join(WIRES)}, got {self.wire!r}")
        if self.krl not in KRL_CONVENTIONS:
            raise ValueError(f"krl must be one of {', '.join(KRL_CONVENTIONS)}, got {self.krl!r}")
        if isinstance(self.fri_cycle_ms, bool) or not isinstance(self.fri_cycle_ms, int) \
                or not 1 <= self.fri_cycle_ms <= 100:
            raise ValueError(f"fri_cycle_ms must be an integer 1..100, got {self.fri_cycle_ms!r}")
        if self.fri_cycle_ms != 1 and (self.wire != "udp" or self.krl == "testbench"):
            raise ValueError(f"fri_cycle_ms {self.fri_cycle_ms}: a cycle other than 1 ms is for a lab's remote over "
                             "UDP (--wire udp --krl frilibrary|lwr_hw): the run's own nodes count 1 ms cycles")
        physics_step(self.physics_substeps)  # a ValueError names what it must be
        host_port(self.fri_remote, "fri_remote")
        host_port(self.fri_bind, "fri_bind", listen=True)

    def world_spec(self):
        step = physics_step(self.physics_substeps)
        if self.world == "valley":
            return valley(Valley(friction=self.plate_friction), timestep=step)
        return WORLDS[self.world](timestep=step)

    def link_faults(self) -> LinkFaults | None:
        """The FRI link's fault model, seeded with the cell's seed (None: a clean link)."""
        return self.fri.link_faults(self.seed)


class RobotNode(Node):
    """The cycle: measure and publish, take the answers, step.  ``fri_udp``: with ``--wire
    udp``, what makes the cell's KRC speak FRI over UDP (the service process brings it:
    ``services.transport.lab``)."""

    name = "robot"

    def __init__(self, config: RobotConfig, bus, clock, *, run_id: str = "", mode: str = "lockstep",
                 sched_fifo=False, fri_udp: Callable | None = None):
        super().__init__(bus, clock)
        if mode not in ("lockstep", "realtime"):
            raise ValueError(f"clock must be lockstep or realtime, got {mode!r}")
        self.config = config
        self.mode = mode
        self.lockstep = mode == "lockstep"
        self.fifo = sched_fifo
        if config.wire == "udp" and self.lockstep:
            raise ValueError("wire udp needs the realtime clock: the KRC sends its measurements on its own clock, "
                             "and a remote over UDP answers on the wall clock")
        if (config.wire == "udp") != (fri_udp is not None):
            raise ValueError(f"wire {config.wire} and {'an' if fri_udp else 'no'} FRI over UDP: the service "
                             "process brings the UDP link with --wire udp (services.transport.lab)")
        # the cell's own F/T sampling is the ft_sensor node's job: not done twice
        self.cell = RobotCell(config.world_spec(), seed=config.seed, faults=config.link_faults(), with_sensor=False,
                              fri_config=FriConfig(cycle_ns=config.fri_cycle_ms * FRI_CYCLE_NS)
                              if config.fri_cycle_ms != 1 else None)
        self.udp = fri_udp(self.cell) if fri_udp is not None else None
        self.relayed = self.udp is not None and self.udp.relayed
        self.labeler = LABELERS[config.world]()
        self.episode = -1
        self.kind = "none"
        self.inbox = AnswerInbox(ANSWER_TOPICS)
        self.ep = EpisodeJudge(0, self.cell.fri.statistics(), 0, self.cell.cycle_ns)
        self._episode_after = None
        self._m = None  # the open cycle's measurement packet, where one is made (FRI over UDP)
        self._seq = self._stamp = self._sent = 0
        self.publications = [Publication(ROBOT_STATE.topic, drop_when_congested=True),
                             Publication(ROBOT_CONTACT.topic, drop_when_congested=True),
                             Publication(EPISODE_SUMMARY.topic, express=False)]
        if self.udp is not None and self.udp.wire_topic:
            self.publications.append(Publication(FRI_DATAGRAM.topic, drop_when_congested=True))
        # realtime needs only what it applies; lockstep also waits on the sensor and the estimator;
        # over UDP the commands come on the FRI socket
        applied = ("teacher",) if self.udp is not None else ("command", "teacher")
        # an answer echoes a measurement: none can be past the latest the KRC sent
        self.subscriptions = [Subscription(topic, self.inbox.handler(name), horizon=self._measured)
                              for name, topic in ANSWER_TOPICS.items() if self.lockstep or name in applied]

    @property
    def sections(self):
        return self.ep.sections

    def _measured(self) -> int:
        """The seq of the latest measurement the KRC sent (the FRI link's)."""
        return self.cell.fri.seq

    def answered(self, names, seq) -> bool:
        if self.udp is not None and not self.udp.answered():
            return False  # the KRC waits for the remote's datagram until the cycle ends
        return self.inbox.has(names, seq)

    # ------------------------------------------------------------- control

    def handlers(self):
        return {"reset": self.reset}

    def reset(self, p: dict) -> dict:
        start = np.asarray(p["start"], dtype=np.float64)
        if start.shape != (3,) or not np.all(np.isfinite(start)):
            raise ValueError(f"start must be 3 finite numbers, got {p['start']!r}")
        kind = p.get("kind", "demonstration")
        if kind not in EPISODE_KINDS:
            raise ValueError(f"kind must be one of {', '.join(EPISODE_KINDS)}, got {kind!r}")
        if kind == "served" and (self.udp is None or self.relayed):
            raise ValueError("an episode of kind served needs --wire udp and a lab's KRL convention "
                             f"(--krl frilibrary or lwr_hw), not wire {self.config.wire}, krl {self.config.krl}")
        if kind != "served" and self.udp is not None and not self.relayed:
            raise ValueError(f"--krl {self.config.krl} serves a lab's remote (episodes of kind served); the run's "
                             f"own episodes over UDP need --krl testbench (kind {kind!r})")
        self.episode = int(p.get("episode", -1))
        self.kind = kind
        cell = self.cell
        q = cell.place_tcp(start, DOWN)
        cell.krc.gravity_compensation = self.kind == "demonstration"
        if cell.fri.state == 0:
            cell.start()
        if self.kind == "reproduction":
            cell.fri.request_command_mode()
        elif self.kind == "demonstration":
            cell.fri.request_monitor_mode()
        # served: the remote asks the KRL program for command mode when it wants it
        self.labeler = LABELERS[self.config.world]()
        self.inbox.clear()
        return {"q": q.tolist(), "seq": cell.fri.seq}

    def plan(self, cmd: str, p: dict) -> EpisodePlan:
        """The run of cycles a 'settle' or 'run' request asks for (ValueError if it makes no sense)."""
        answers = tuple(p.get("wait_for", []))
        if cmd == "settle":
            n = int(p.get("cycles", 200))
            if n < 1:
                raise ValueError(f"cycles must be >= 1, got {n}")
            return EpisodePlan(max_cycles=n, answers_from=answers, cycles=n)
        seconds = float(p.get("max_seconds", 40.0))
        if not (np.isfinite(seconds) and seconds > 0):
            raise ValueError(f"max_seconds must be > 0, got {p.get('max_seconds')!r}")
        return EpisodePlan(max_cycles=max(1, round(seconds * 1e9 / self.cell.cycle_ns)), answers_from=answers,
                           stop_on=p.get("stop_on"))

    def status(self) -> dict:
        status = {"episode": self.episode, "seq": self.cell.fri.seq, "fri_state": int(self.cell.fri.state),
                  "safety": int(self.cell.krc.safety), "fifo": self.fifo}
        if self.udp is not None:
            status["fri_udp"] = self.udp.status()
        return status

    def close(self) -> None:
        if self.udp is not None:
            self.udp.close()

    # ------------------------------------------------------------- episodes

    def begin_episode(self, settle: bool = False) -> None:
        """Before a run of cycles.  A settle's cycles (the arm resting while the sensor
        is tared) belong to no episode: the estimator and the commander do not take
        them as one."""
        self._episode_after = None
        if settle:
            self._episode_after, self.episode = self.episode, -1
        self.ep = EpisodeJudge(self.cell.fri.seq + 1, self.cell.fri.statistics(), self.clock.now_ns(),
                               self.cell.cycle_ns)
        if self.udp is not None:
            self.udp.begin_episode()

    def end_episode(self, engine) -> dict:
        """After a run of cycles: its summary (what robot/episode carries)."""
        try:
            return self.ep.summary(engine, self.cell, episode=self.episode, kind=self.kind, now_ns=self.clock.now_ns(),
                                   clock=self.mode, sched_fifo=self.fifo,
                                   wire=self.udp.summary(self.ep) if self.udp is not None else None)
        finally:
            if self._episode_after is not None:
                self.episode, self._episode_after = self._episode_after, None

    def publish_summary(self, summary: dict) -> None:
        self.bus.publish(EPISODE_SUMMARY.topic, EPISODE_SUMMARY.encode(**summary))

    # --------------------------------------------------------------- cycles

    def open_cycle(self) -> tuple[int, int]:
        """Measure and publish: the FRI measurement (first: it is what the commander answers)
        and the physics' truth."""
        bus, now = self.bus, self.clock.now_ns
        state = self.measure_state()
        t = now()
        if not self.relayed:
            bus.publish(ROBOT_STATE.topic, *state)
        self.ep.sections.add("publish", now() - t)
        contact = self.measure_contact()
        t = now()
        bus.publish(ROBOT_CONTACT.topic, *contact)
        self.ep.sections.add("publish", now() - t)
        return self._seq, self._stamp

    # what opening a cycle measures, each as ``pack`` gives it (payload, message), for whoever
    # carries them: ``open_cycle``, or an engine that steps the nodes itself (services.transport.fused)

    def measure_state(self) -> tuple:
        """Open a cycle: the FRI measurement, ``robot/state``."""
        cell, sec, now = self.cell, self.ep.sections, self.clock.now_ns
        krc = cell.krc
        t0 = now()
        stamp = cell.t_ns
        if self.udp is not None:  # the datagram is made from the packet
            m = cell.begin_cycle()
            self.udp.send(m, episode=self.episode, kind=self.kind, gravity_compensation=bool(krc.gravity_compensation))
            seq = m.seq
        else:
            m, seq = None, cell.measure()
        sent = now()
        sec.add("measure", sent - t0)
        if m is not None:
            state = state_message(m, sent_ns=sent, safety=int(krc.safety),
                                  gravity_compensation=bool(krc.gravity_compensation), episode=self.episode)
        else:
            state = measured_state(cell.fri, seq, stamp, *cell.measured_views(), sent_ns=sent,
                                   safety=int(krc.safety), gravity_compensation=bool(krc.gravity_compensation),
                                   episode=self.episode)
        sec.add("encode", now() - sent)
        self._m, self._seq, self._stamp, self._sent = m, seq, stamp, sent
        return state

    def measure_contact(self) -> tuple:
        """The open cycle's physics' truth, ``robot/contact``."""
        cell, ep, seq, now = self.cell, self.ep, self._seq, self.clock.now_ns
        t0 = now()
        # the cell's own buffers: pack copies them into the message (the touching list too)
        wrench, contact, touching, pose, twist = cell.truth_views()
        true_phase = self.labeler.update(touching)
        ep.measured(seq, self._sent, math.hypot(contact[0], contact[1], contact[2]))
        t1 = now()
        packed = ROBOT_CONTACT.pack(
            seq=seq, stamp_ns=self._stamp, sent_ns=t1, wrench=wrench, contact_force=contact,
            touching=list(touching), true_phase=true_phase, tcp_pose=pose, tcp_twist=twist, episode=self.episode)
        ep.sections.add("measure", t1 - t0)
        ep.sections.add("encode", now() - t1)
        return packed

    def close_cycle(self, stop_on) -> str | None:
        """Hand the open cycle's answers to the FRI link, apply the hand, step; the judge
        says whether the episode ends (why, or None)."""
        return self.apply(*self.inbox.take(self._seq), stop_on)

    def apply(self, commands, teacher_entry, latest_teacher, stop_on) -> str | None:
        """Close the open cycle with these answers (``AnswerInbox.take``'s three): the commands
        to the FRI link, the hand, the step; the judge says whether the episode ends."""
        cell, ep, open_seq, sent = self.cell, self.ep, self._seq, self._sent
        sec = ep.sections
        t0 = self.clock.now_ns()
        faults = cell.fri.faults
        if faults is not None:
            faults.active = self.config.fri.active(ep.k * cell.cycle_ns / 1e9)
        goal_reached = teacher_done = False
        cycle_hold = None  # this cycle's command: why it holds ('' it does not); None: no command
        cycle_estimate = -1  # the estimate this cycle's command used
        if self.udp is not None:
            taken = self.udp.take(self._m)
            if taken is not None:
                ep.answer.add(taken.latency_ns)
            if taken is not None and self.relayed:
                # the testbench's remote says on the KRL channels what a robot/command says
                goal_reached, cycle_hold, cycle_estimate = taken.goal_reached, taken.hold, taken.estimate_seq
                if goal_reached:
                    ep.goal_reached()
                ep.estimate_used(cycle_estimate, taken.arrived_ns)
        for seq, (msg, recv) in commands:
            sent_at = sent if seq == open_seq else ep.sent.get(seq)
            if sent_at is None:  # an answer to a cycle of no episode of ours
                continue
            ep.answer.add(recv - sent_at)
            est = msg.get("estimate_seq", -1)
            ep.estimate_used(est, recv)
            stamp = self._stamp - (open_seq - seq) * cell.cycle_ns
            arrival = stamp + (LOCKSTEP_LATENCY_NS if self.lockstep else recv - sent_at)
            deliver_command(cell.fri, msg, arrival)
            if seq == open_seq:
                goal_reached = bool(msg["goal_reached"])
                if goal_reached:
                    ep.goal_reached()
                cycle_hold = msg["hold"]
                cycle_estimate = est
        teacher_msg = teacher_entry[0] if teacher_entry is not None else (None if self.lockstep else latest_teacher)
        hand = None
        # episode indices count demonstrations and reproductions separately: the teacher
        # still set up for demonstration 5 answered reproduction 5 and pushed the arm
        if teacher_msg is not None and teacher_msg["episode"] == self.episode and self.kind == "demonstration":
            hand = np.array(teacher_msg["wrench"])
            teacher_done = bool(teacher_msg["done"])
        t1 = self.clock.now_ns()
        try:
            outcome = cell.close(hand)
        finally:
            t2 = self.clock.now_ns()
            # they crossed the wire, whatever the step did
            if self.udp is not None and self.udp.publish_datagrams(self.bus):
                sec.add("publish", self.clock.now_ns() - t2)
        sec.add("answers", t1 - t0)
        sec.add("step", t2 - t1)
        return ep.judge(cell, outcome, open_seq, kind=self.kind, stop_on=stop_on, teacher_done=teacher_done,
                        goal_reached=goal_reached, hold=cycle_hold, estimate_seq=cycle_estimate,
                        track_states=self.udp is not None)
