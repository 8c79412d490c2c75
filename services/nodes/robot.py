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

import dataclasses
import math
import threading
from dataclasses import dataclass

import numpy as np

from robot_sim.cell import RobotCell
from robot_sim.cycle import FRI_CYCLE_NS, FRI_RATE_HZ
from robot_sim.krc.faults import LinkFaultSpec, LinkFaults
from robot_sim.krc.link import FriConfig
from robot_sim.krc.packets import CommandPacket, ControlMode, FriQuality, FriState
from robot_sim.wire.fri_udp import host_port
from robot_sim.wire.fri_datagrams import REMOTE_PORT
from robot_sim.krc.law import SafetyReason
from robot_sim.krc_udp import UdpKrc
from robot_sim.krc.krl import (KRL_CONVENTIONS, TB_EPISODE, TB_ESTIMATE_SEQ, TB_GOAL_REACHED,
                               TB_GRAVITY_COMPENSATION, TB_HOLD, TB_HOLDS, TB_KIND, TB_KINDS)
from robot_sim.world.labels import LABELERS
from robot_sim.world.teacher import DOWN
from robot_sim.world.tasks import TASK_WORLDS, Valley, WORLDS, physics_step, valley
from services.runtime.bus import Node, Publication, Subscription
from services.runtime.config import nested, option
from services.runtime.cycle import EpisodePlan
from services.runtime.roles import PARTICIPANTS, ROLES
from services.runtime.loop import Sections
from services.runtime.messages import (EPISODE_SUMMARY, FRI_DATAGRAM, HOLD_WATCH_S, ROBOT_CONTACT, ROBOT_STATE,
                                       datagram_fields)
from services.runtime.timing import Histogram

LOCKSTEP_LATENCY_NS = 100_000
HOLD_WATCH_CYCLES = int(HOLD_WATCH_S * FRI_RATE_HZ)
# per-cycle sections (episode summary, loop.sections): waiting for the deadline or the
# answers, handing the answers to the FRI link, the physics step (KRC law + MuJoCo +
# sensing), measuring (FRI packet, labels), encoding, publishing
SECTIONS = ("wait", "answers", "step", "measure", "encode", "publish")
ANSWER_TOPICS = {participant: ROLES[role].answer_topic for participant, role in PARTICIPANTS.items()}
WIRES = ("zenoh", "udp")
EPISODE_KINDS = ("demonstration", "reproduction", "served")


@dataclass(frozen=True)
class RobotConfig:
    world: str = option("valley", "task world", choices=TASK_WORLDS)
    seed: int = option(0, "seed of the cell (joint measurement noise)")
    answer_timeout: float = option(5.0, "lockstep: seconds to wait for a cycle's answers before counting a miss",
                                   metavar="S")
    stall_every: float = option(0.0, "fault injection: stall the loop every S seconds (0: never)", metavar="S")
    stall_ms: float = option(0.0, "fault injection: how long each stall lasts, ms", metavar="MS")
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
        if not self.answer_timeout > 0:
            raise ValueError(f"answer_timeout must be > 0 s, got {self.answer_timeout!r}")
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


class _Episode:
    """What one run of cycles accumulates for its summary."""

    def __init__(self, first_seq: int, fri0, wall0_ns: int):
        self.first_seq = first_seq
        self.fri0 = fri0  # the link's counters run for its whole session: report this episode's
        self.wall0_ns = wall0_ns
        self.peak = 0.0
        self.answer = Histogram()
        self.closed_loop = Histogram()
        self.sent: dict[int, int] = {}
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
        self.states: list = []  # udp: the link's state changes (seq, state, quality)
        self.refusals: list = []  # udp: first commands the KRC refused (seq, at_s, reason)
        self.krl_events = 0  # the KRL program's events before this episode
        self.wire0 = None  # the UDP endpoint's counters when the episode began
        self.safety_stop = None  # served: the KRC's safety stop (seq, at_s, reason)
        self.fri_state = fri0.state  # the link keeps its state from one episode into the next
        self.k = 0
        self.sections = Sections(*SECTIONS)


class RobotNode(Node):
    name = "robot"

    def __init__(self, config: RobotConfig, bus, clock, *, run_id: str = "", mode: str = "lockstep",
                 sched_fifo=False):
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
        # the cell's own F/T sampling is the ft_sensor node's job: not done twice
        self.cell = RobotCell(config.world_spec(), seed=config.seed, faults=config.link_faults(), with_sensor=False,
                              fri_config=FriConfig(cycle_ns=config.fri_cycle_ms * FRI_CYCLE_NS)
                              if config.fri_cycle_ms != 1 else None)
        self.udp = None
        # --krl testbench: the run's own commander is the remote; it passes each measurement on
        # as robot/state (as the lab's FRI component did for its graph), so the robot does not
        self.relayed = config.wire == "udp" and config.krl == "testbench"
        if config.wire == "udp":
            self.udp = UdpKrc(self.cell, host_port(config.fri_remote, "fri_remote"),
                              host_port(config.fri_bind, "fri_bind", listen=True), krl=config.krl,
                              clock=clock.now_ns)
        self.labeler = LABELERS[config.world]()
        self.episode = -1
        self.kind = "none"
        # answers arrive on transport threads (Zenoh) while the engine's thread closes cycles
        self.arrived = threading.Condition()
        self.arrivals = 0  # bumped with every awaited answer: a transport waits for it to change
        # the participants the episode in progress waits for: another's answer is stored
        # but wakes nobody (over Zenoh the sensor's answer to every cycle of a
        # demonstration woke the engine's thread for nothing, a context switch a cycle)
        self.awaited: frozenset = frozenset(ANSWER_TOPICS)
        self._answers: dict[str, dict] = {name: {} for name in ANSWER_TOPICS}
        self._latest_teacher = None
        self.ep = _Episode(0, self.cell.fri.statistics(), 0)
        self.sections = self.ep.sections
        self._episode_after = None
        self._m = None
        self._datagrams: list = []  # (seq, stamp_ns, sent_ns, direction, bytes) of the open cycle, for fri/datagram
        self._sent = 0
        self.publications = [Publication("robot/state", drop_when_congested=True),
                             Publication("robot/contact", drop_when_congested=True),
                             Publication("robot/episode", express=False)]
        self.wire_topic = self.udp is not None and config.wire_topic
        if self.wire_topic:
            self.publications.append(Publication("fri/datagram", drop_when_congested=True))
        # realtime needs only what it applies; lockstep also waits on the sensor and the estimator;
        # over UDP the commands come on the FRI socket
        applied = ("teacher",) if self.udp is not None else ("command", "teacher")
        self.subscriptions = [Subscription(topic, self._on_answer(name)) for name, topic in ANSWER_TOPICS.items()
                              if self.lockstep or name in applied]

    # ------------------------------------------------------------- arrivals

    def _on_answer(self, name):
        store = self._answers[name]

        def handler(msg, recv_ns, raw):
            with self.arrived:
                store[msg["seq"]] = (msg, recv_ns)
                if len(store) > 4000:  # keep memory bounded on long realtime runs
                    for k in sorted(store)[:2000]:
                        del store[k]
                if name == "teacher":
                    self._latest_teacher = msg
                if name in self.awaited:
                    self.arrivals += 1
                    self.arrived.notify_all()
        return handler

    def answered(self, names, seq) -> bool:
        if self.udp is not None and not self.udp.answered():
            return False  # the KRC waits for the remote's datagram until the cycle ends
        answers = self._answers
        for n in names:
            if seq not in answers[n]:
                return False
        return True

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
        with self.arrived:
            for store in self._answers.values():
                store.clear()
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
            status["fri_udp"] = {"address": list(self.udp.address), "remote": list(self.udp.remote),
                                 "krl": self.config.krl}
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
        self.ep = _Episode(self.cell.fri.seq + 1, self.cell.fri.statistics(), self.clock.now_ns())
        self.sections = self.ep.sections
        # a cycle an earlier episode opened and never closed (it failed mid-cycle): its
        # measurement's copy is not this episode's to record
        self._datagrams.clear()
        if self.udp is not None:
            self.ep.krl_events = len(self.udp.krl.events)
            self.ep.wire0 = dataclasses.replace(self.udp.endpoint.counters)

    def end_episode(self, engine) -> dict:
        """After a run of cycles: its summary (what robot/episode carries)."""
        try:
            return self._summary(engine)
        finally:
            if self._episode_after is not None:
                self.episode, self._episode_after = self._episode_after, None

    def _summary(self, engine) -> dict:
        cell, ep = self.cell, self.ep
        stats = cell.fri.statistics()
        now = self.clock.now_ns()
        fri0 = ep.fri0
        return dict(
            seq=cell.fri.seq, stamp_ns=cell.t_ns, sent_ns=now, episode=self.episode, kind=self.kind,
            reason=engine.reason, first_seq=ep.first_seq, last_seq=cell.fri.seq,
            sim_seconds=engine.k * cell.cycle_ns / 1e9, wall_seconds=(now - ep.wall0_ns) / 1e9,
            final_position=cell.sim.tcp_position(), peak_contact_force=ep.peak, safety=int(cell.krc.safety),
            missed_answers=engine.missed_answers, goal_reached_at_s=ep.goal_at,
            **({"hold": dict(ep.hold)} if ep.hold is not None else {}),
            fri={"answered": stats.answered - fri0.answered, "missed": stats.missed - fri0.missed,
                 "late": stats.late - fri0.late, "corrupt": stats.corrupt - fri0.corrupt,
                 "duplicate": stats.duplicate - fri0.duplicate, "longest_miss_run": ep.miss_run,
                 "command_mode_entered": ep.cmd_entered, "command_mode_left": ep.cmd_left,
                 "state": int(stats.state), "quality": int(stats.quality)},
            loop=dict(engine.timing.summary(), clock=self.mode, sched_fifo=self.fifo,
                      answer_latency=ep.answer.to_dict(), closed_loop_latency=ep.closed_loop.to_dict(),
                      sections=ep.sections.summary(), wall_start_ns=ep.wall0_ns, wall_end_ns=now),
            **({"wire": self._wire_summary(engine)} if self.udp is not None else {}),
        )

    # --------------------------------------------------------------- FRI over UDP

    def _send_datagram(self, m) -> None:
        if self.relayed:
            krl = self.udp.krl.krl_to
            krl.ints[TB_EPISODE - 1] = self.episode
            krl.ints[TB_KIND - 1] = TB_KINDS.index(self.kind) if self.episode >= 0 else 0
            krl.set_flag(TB_GRAVITY_COMPENSATION, bool(self.cell.krc.gravity_compensation))
        if self.udp.send(m) and self.wire_topic:
            self._datagrams.append((m.seq, m.stamp_ns, self.udp.sent_ns, "measurement", self.udp.last_sent))

    def _take_datagram(self, m):
        """The open cycle's command datagram, if it came: (goal reached, hold, estimate seq)
        from its KRL block (what the testbench's remote says there), else None."""
        udp = self.udp
        if udp.take(m) is None:
            return None
        self.ep.answer.add(udp.latency_ns)
        if self.wire_topic:
            self._datagrams.append((m.seq, m.stamp_ns, udp.sent_ns + udp.latency_ns, "command", udp.last_accepted))
        frm = udp.endpoint.krl_accepted
        hold = int(frm.ints[TB_HOLD - 1])
        return (frm.flag(TB_GOAL_REACHED), TB_HOLDS[hold] if 0 <= hold < len(TB_HOLDS) else "other",
                int(frm.ints[TB_ESTIMATE_SEQ - 1]))

    def _publish_datagrams(self) -> None:
        """The cycle's datagrams on fri/datagram, once it has stepped: decoding one for the
        recording costs as much as the cycle's physics (~70 us), and made where it crossed
        the wire it kept the remote's answer waiting, then the step."""
        for seq, stamp_ns, sent_ns, direction, data in self._datagrams:
            self.bus.publish("fri/datagram", *FRI_DATAGRAM.pack(
                seq=seq, stamp_ns=stamp_ns, sent_ns=sent_ns, direction=direction,
                **datagram_fields(data, direction)))
        self._datagrams.clear()

    def _wire_summary(self, engine) -> dict:
        ep, udp, krl = self.ep, self.udp, self.udp.krl
        counters = {k: v - getattr(ep.wire0, k) for k, v in dataclasses.asdict(udp.endpoint.counters).items()}
        return {"address": f"{udp.address[0]}:{udp.address[1]}", "remote": f"{udp.remote[0]}:{udp.remote[1]}",
                "krl": self.config.krl, "datagrams": counters, "last_reject_reason": udp.endpoint.last_reject_reason,
                "krl_events": [dict(seq=e.seq, at_s=(e.seq - ep.first_seq + 1) * self.cell.cycle_ns / 1e9,
                                    kind=e.kind, text=e.text) for e in krl.events[ep.krl_events:]],
                "refusal": krl.refusal, "first_command_refusals": list(ep.refusals),
                "safety_stop": ep.safety_stop,
                "command_mode_s": ep.cmd_cycles * self.cell.cycle_ns / 1e9,
                "states": [dict(seq=q, at_s=(q - ep.first_seq + 1) * self.cell.cycle_ns / 1e9,
                                state=FriState(st).name, quality=FriQuality(qu).name) for q, st, qu in ep.states],
                "control_mode": ControlMode(self.cell.fri.control_mode).name}

    def publish_summary(self, summary: dict) -> None:
        self.bus.publish("robot/episode", EPISODE_SUMMARY.encode(**summary))

    # --------------------------------------------------------------- cycles

    def open_cycle(self) -> tuple[int, int]:
        """Measure and publish: the FRI measurement and the physics' truth."""
        cell, ep, sec, now = self.cell, self.ep, self.ep.sections, self.clock.now_ns
        t0 = now()
        m = cell.begin_cycle()
        if self.udp is not None:
            self._send_datagram(m)
        sent = now()
        sec.add("measure", sent - t0)
        state = ROBOT_STATE.pack(
            seq=m.seq, stamp_ns=m.stamp_ns, sent_ns=sent, reflected_seq=m.reflected_seq,
            fri_state=int(m.state), fri_quality=int(m.quality), control_mode=int(m.control_mode),
            msr_jnt_pos=m.msr_jnt_pos, msr_cart_pos=m.msr_cart_pos, est_ext_tcp_ft=m.est_ext_tcp_ft,
            answer_rate=m.answer_rate, latency_s=m.latency_s, jitter_s=m.jitter_s, miss_rate=m.miss_rate,
            safety=int(cell.krc.safety), gravity_compensation=bool(cell.krc.gravity_compensation),
            episode=self.episode)
        t1 = now()
        if not self.relayed:
            self.bus.publish("robot/state", *state)
        t2 = now()
        sec.add("encode", t1 - sent)
        sec.add("publish", t2 - t1)
        wrench, contact, touching = cell.tool_wrench, cell.contact_force, cell.touching
        true_phase = self.labeler.update(touching)
        force = math.hypot(contact[0], contact[1], contact[2])
        if force > ep.peak:
            ep.peak = force
        ep.sent[m.seq] = sent
        if len(ep.sent) > 2000:  # the closed loop spans a few cycles: forget the old ones
            for old in [k for k in ep.sent if k < m.seq - 1000]:
                del ep.sent[old]
        t3 = now()
        contact_msg = ROBOT_CONTACT.pack(
            seq=m.seq, stamp_ns=m.stamp_ns, sent_ns=t3, wrench=wrench, contact_force=contact,
            touching=touching, true_phase=true_phase, tcp_pose=cell.true_tcp_pose, tcp_twist=cell.true_tcp_twist,
            episode=self.episode)
        t4 = now()
        self.bus.publish("robot/contact", *contact_msg)
        sec.add("measure", t3 - t2)
        sec.add("encode", t4 - t3)
        sec.add("publish", now() - t4)
        self._m, self._sent = m, sent
        return m.seq, m.stamp_ns

    def close_cycle(self, stop_on) -> str | None:
        """Hand the open cycle's answers to the FRI link, apply the hand, step.
        Returns why the episode ends, or None."""
        cell, ep, m, sent = self.cell, self.ep, self._m, self._sent
        sec = ep.sections
        t0 = self.clock.now_ns()
        with self.arrived:
            # every answer that came since the last close: this cycle's, and late ones
            # for cycles already closed, which the FRI link must see to count them late
            commands = self._answers["command"]
            cmd_entries = sorted(commands.items()) if commands else ()
            commands.clear()
            teacher_entry = self._answers["teacher"].pop(m.seq, None)
            latest_teacher = self._latest_teacher
        faults = cell.fri.faults
        if faults is not None:
            faults.active = self.config.fri.active(ep.k * cell.cycle_ns / 1e9)
        goal_reached = teacher_done = False
        cycle_hold = None  # this cycle's command: why it holds ('' it does not); None: no command
        cycle_estimate = -1  # the estimate this cycle's command used
        if self.udp is not None:
            taken = self._take_datagram(m)
            if taken is not None and self.relayed:
                # the testbench's remote says on the KRL channels what a robot/command says
                goal_reached, cycle_hold, cycle_estimate = taken
                if goal_reached and ep.goal_at < 0:
                    ep.goal_at = ep.k * cell.cycle_ns / 1e9
                if cycle_estimate > ep.last_estimate and cycle_estimate in ep.sent:
                    # closed loop: this cycle's measurement -> sensor -> estimator -> commander -> here
                    ep.closed_loop.add(self.udp.sent_ns + self.udp.latency_ns - ep.sent[cycle_estimate])
                    ep.last_estimate = cycle_estimate
        for seq, (msg, recv) in cmd_entries:
            sent_at = sent if seq == m.seq else ep.sent.get(seq)
            if sent_at is None:  # an answer to a cycle of no episode of ours
                continue
            ep.answer.add(recv - sent_at)
            est = msg.get("estimate_seq", -1)
            if est > ep.last_estimate and est in ep.sent:
                # closed loop: this cycle's measurement -> sensor -> estimator -> commander -> here
                ep.closed_loop.add(recv - ep.sent[est])
                ep.last_estimate = est
            stamp = m.stamp_ns - (m.seq - seq) * cell.cycle_ns
            arrival = stamp + (LOCKSTEP_LATENCY_NS if self.lockstep else recv - sent_at)
            # made here from the message's lists, in float64 as the link's copy would be: the
            # link keeps this packet instead of copying it again
            cell.deliver(CommandPacket(seq=msg["seq"], cart_pos=np.array(msg["cart_pos"], dtype=np.float64),
                                       cart_stiffness=np.array(msg["cart_stiffness"], dtype=np.float64),
                                       cart_damping=np.array(msg["cart_damping"], dtype=np.float64),
                                       add_tcp_ft=np.array(msg["add_tcp_ft"], dtype=np.float64),
                                       requested_mode=ControlMode(msg["requested_mode"])), arrival, owned=True)
            if seq == m.seq:
                goal_reached = bool(msg["goal_reached"])
                if goal_reached and ep.goal_at < 0:
                    ep.goal_at = ep.k * cell.cycle_ns / 1e9
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
            outcome = cell.end_cycle(hand).outcome
        finally:
            t2 = self.clock.now_ns()
            if self._datagrams:  # they crossed the wire, whatever the step did
                self._publish_datagrams()
                sec.add("publish", self.clock.now_ns() - t2)
        sec.add("answers", t1 - t0)
        sec.add("step", t2 - t1)
        ep.k += 1
        if outcome.state != ep.fri_state:
            if outcome.state == FriState.CMD:
                ep.cmd_entered += 1
            elif ep.fri_state == FriState.CMD:
                ep.cmd_left += 1
            ep.fri_state = outcome.state
        if outcome.state == FriState.CMD:
            ep.cmd_cycles += 1
        if self.udp is not None and (not ep.states or ep.states[-1][1:] != (int(outcome.state), int(outcome.quality))):
            ep.states.append((m.seq, int(outcome.state), int(outcome.quality)))
        ep.run = 0 if outcome.answered else ep.run + 1
        ep.miss_run = max(ep.miss_run, ep.run)
        fri = cell.fri
        if cell.first_command_refused:
            ep.refusals.append(dict(seq=m.seq, at_s=ep.k * cell.cycle_ns / 1e9, reason=cell.first_command_refused))
            cell.first_command_refused = ""
        if self.kind == "reproduction" and fri.state == FriState.MON and not fri.command_requested:
            # as the KRL program of a lab set-up does: after a fall-back to monitor
            # mode, ask for command mode again (entered once the link is PERFECT again)
            fri.request_command_mode()
        for flag, name in ((teacher_done, "teacher_done"), (goal_reached, "goal_reached")):
            if flag and stop_on == name:
                return name
        if cycle_hold:
            if ep.hold is None:
                ep.hold = dict(reason=cycle_hold, seq=m.seq, at_s=(ep.k - 1) * cell.cycle_ns / 1e9,
                               estimate_seq=cycle_estimate, cycles=0, max_displacement_m=0.0,
                               peak_contact_force=0.0)
            if ep.hold_run == 0:
                ep.hold_x0 = cell.sim.tcp_position()
            ep.hold_run += 1
            # what the arm does while the commander holds it: how far the tcp goes, how hard it presses
            h = ep.hold
            h["cycles"] += 1
            h["max_displacement_m"] = max(h["max_displacement_m"],
                                          float(np.linalg.norm(cell.sim.tcp_position() - ep.hold_x0)))
            h["peak_contact_force"] = max(h["peak_contact_force"], math.hypot(*cell.contact_force[:3]))
            if ep.hold_run >= HOLD_WATCH_CYCLES:
                return f"hold:{h['reason']}"
        elif cycle_hold is not None:
            ep.hold_run = 0
        if cell.krc.safety != 0:
            reason = SafetyReason(cell.krc.safety).name.lower()
            if self.kind != "served":
                return f"safety:{reason}"
            if ep.safety_stop is None:
                # a lab's remote is served on: the KRC has dropped it to monitor mode, holds the
                # arm and reports the error in the measurement (RobotCell.remote_checks)
                ep.safety_stop = dict(seq=m.seq, at_s=ep.k * cell.cycle_ns / 1e9, reason=reason)
        return None
