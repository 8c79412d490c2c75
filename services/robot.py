"""robot: the simulated LWR4+ behind its KRC/FRI link, one process, 1 kHz.

Every FRI cycle it publishes ``robot/state`` (the FRI measurement) and
``robot/contact`` (the physics' truth for the F/T sensor and the labels),
applies the impedance commander's answer (``robot/command``, echoing the
measurement's seq) and the teacher's hand (``teacher/wrench``), and steps the
physics.  Clocks:

- ``realtime``: cycles on absolute 1 ms deadlines; an answer counts for the
  FRI link if it arrived before the cycle's deadline (its simulated arrival
  time is the measured latency after the measurement).
- ``lockstep``: a cycle ends only when every participant named in the run
  request has answered it (or ``answer_timeout`` passes: then the FRI link
  counts a miss); answers are taken to arrive 0.1 ms after the measurement.
  Simulated time runs as fast as the slowest participant; same seed, same run.

Episodes are driven by the runner through control requests: ``reset``,
``settle``, ``run``, ``stop``, ``shutdown`` (see ``RobotProcess.handle``).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from robot_sim.cell import RobotCell
from robot_sim.fri import CommandPacket, ControlMode, FriState
from robot_sim.krc import SafetyReason
from robot_sim.labels import LABELERS
from robot_sim.teacher import DOWN
from robot_sim.worlds import WORLDS
from services.runtime.loop import AbsoluteDeadlineTimer, LoopTiming, Sections, set_timer_slack
from services.runtime.timing import Histogram
from services.runtime.messages import EPISODE_SUMMARY, ROBOT_CONTACT, ROBOT_STATE
from services.runtime.service import Service, now_ns
from services.runtime.session import ZenohOptions, add_sched_fifo_argument, add_zenoh_arguments, zenoh_options

LOCKSTEP_LATENCY_NS = 100_000
# per-cycle sections of the loop (episode summary, loop.sections): waiting for the
# deadline or the answers, handing the answers to the FRI link, the physics step
# (KRC law + MuJoCo + sensing), measuring (FRI packet, labels), encoding, publishing
SECTIONS = ("wait", "answers", "step", "measure", "encode", "publish")
ANSWER_TOPICS = {"command": "robot/command", "teacher": "teacher/wrench", "ft": "ft/wrench",
                 "phase": "estimator/phase"}


@dataclass(frozen=True)
class RobotConfig:
    run_id: str
    zenoh: ZenohOptions
    clock: str = "lockstep"
    world: str = "valley"
    seed: int = 0
    answer_timeout_s: float = 5.0
    sched_fifo: int = 0  # SCHED_FIFO priority for the whole process, 0: none
    cpus: tuple = ()  # CPU affinity of the whole process, (): any
    stall_every_s: float = 0.0  # fault injection (issue 5): stall the loop periodically
    stall_ms: float = 0.0


class RobotProcess:
    def __init__(self, config: RobotConfig, service: Service):
        if config.clock not in ("lockstep", "realtime"):
            raise ValueError(f"clock must be lockstep or realtime, got {config.clock!r}")
        if config.world not in WORLDS:
            raise ValueError(f"world {config.world!r} unknown (known: {sorted(WORLDS)})")
        self.config = config
        self.svc = service
        self.cell = RobotCell(WORLDS[config.world](), seed=config.seed)
        self.labeler = LABELERS[config.world]()
        self.episode = -1
        self.kind = "none"
        self._cond = threading.Condition()
        self._answers: dict[str, dict] = {name: {} for name in ANSWER_TOPICS}
        self._latest_teacher = None
        realtime = config.clock == "realtime"
        self._pub_state = service.publisher("robot/state", drop_when_congested=realtime)
        self._pub_contact = service.publisher("robot/contact", drop_when_congested=realtime)
        self._pub_episode = service.publisher("robot/episode", realtime=False)
        for name, topic in ANSWER_TOPICS.items():
            # realtime needs only what it applies; lockstep also waits on the sensor and the estimator
            if config.clock == "lockstep" or name in ("command", "teacher"):
                service.subscribe(topic, self._on_answer(name))
        self.fifo = service.sched_fifo
        set_timer_slack(1)

    # ------------------------------------------------------------- arrivals

    def _on_answer(self, name):
        def handler(msg, recv_ns, raw):
            with self._cond:
                store = self._answers[name]
                store[msg["seq"]] = (msg, recv_ns)
                if len(store) > 4000:  # keep memory bounded on long realtime runs
                    for k in sorted(store)[:2000]:
                        del store[k]
                if name == "teacher":
                    self._latest_teacher = msg
                self._cond.notify_all()
        return handler

    def _wait_for(self, names, seq) -> bool:
        deadline = time.monotonic() + self.config.answer_timeout_s
        with self._cond:
            while True:
                missing = [n for n in names if seq not in self._answers[n]]
                if not missing:
                    return True
                left = deadline - time.monotonic()
                if left <= 0 or self.svc.stop.is_set():
                    return False
                self._cond.wait(min(left, 0.05))

    # ------------------------------------------------------------- control

    def serve(self) -> None:
        while not self.svc.stop.is_set():
            req = self.svc.next_control(timeout=0.05)
            if req is None:
                continue
            try:
                if self.handle(req) == "shutdown":
                    return
            except Exception as exc:  # a bad request must not kill the robot
                self.svc.log(f"control '{req.cmd}' failed: {type(exc).__name__}: {exc}")
                req.fail(f"{type(exc).__name__}: {exc}")

    def handle(self, req):
        p = req.payload
        if req.cmd == "reset":
            start = np.asarray(p["start"], dtype=np.float64)
            if start.shape != (3,) or not np.all(np.isfinite(start)):
                raise ValueError(f"start must be 3 finite numbers, got {p['start']!r}")
            self.episode = int(p.get("episode", -1))
            self.kind = p.get("kind", "demonstration")
            cell = self.cell
            q = cell.place_tcp(start, DOWN)
            cell.krc.gravity_compensation = self.kind == "demonstration"
            if cell.fri.state == 0:
                cell.start()
            if self.kind == "reproduction":
                cell.fri.request_command_mode()
            else:
                cell.fri.request_monitor_mode()
            self.labeler = LABELERS[self.config.world]()
            with self._cond:
                for store in self._answers.values():
                    store.clear()
            req.reply(q=q.tolist(), seq=cell.fri.seq)
        elif req.cmd == "settle":
            # the arm rests while the sensor is tared: these cycles belong to no
            # episode, so the estimator and the commander do not take them as one
            n = int(p.get("cycles", 200))
            episode, self.episode = self.episode, -1
            try:
                summary = self.run_cycles(n, list(p.get("wait_for", [])), stop_on=None, max_cycles=n)
            finally:
                self.episode = episode
            req.reply(**summary)
        elif req.cmd == "run":
            wait_for = list(p.get("wait_for", []))
            unknown = set(wait_for) - set(ANSWER_TOPICS)
            if unknown:
                raise ValueError(f"wait_for: unknown participants {sorted(unknown)}")
            max_cycles = int(float(p.get("max_seconds", 40.0)) * 1000)
            req.reply(started=True, seq=self.cell.fri.seq + 1)
            summary = self.run_cycles(None, wait_for, stop_on=p.get("stop_on"), max_cycles=max_cycles)
            self._pub_episode.put(EPISODE_SUMMARY.encode(**summary))
        elif req.cmd == "shutdown":
            req.reply()
            return "shutdown"
        elif req.cmd == "status":
            req.reply(episode=self.episode, seq=self.cell.fri.seq, fri_state=int(self.cell.fri.state),
                      safety=int(self.cell.krc.safety), fifo=self.fifo, links={k: v.to_dict() for k, v in
                                                                               self.svc.links.items()})
        else:
            raise ValueError(f"unknown command {req.cmd!r} (reset, settle, run, status, shutdown)")
        return None

    def _stop_requested(self) -> bool:
        """During an episode only 'stop' (and 'status') are served; the rest wait."""
        req = self.svc.next_control()
        if req is None:
            return False
        if req.cmd == "stop":
            req.reply()
            return True
        if req.cmd == "status":
            req.reply(episode=self.episode, seq=self.cell.fri.seq, running=True)
        else:
            req.fail(f"busy running episode {self.episode}: only 'stop' and 'status' are served now")
        return False

    # --------------------------------------------------------------- cycles

    def run_cycles(self, n, wait_for, stop_on, max_cycles) -> dict:
        """Run FRI cycles until ``n`` are done, a stop condition holds or
        ``max_cycles`` pass; returns the episode summary.

        lockstep: open a cycle (measure, publish), wait for the awaited answers,
        close it (apply them, step).  realtime: at every 1 ms deadline close the
        cycle opened at the previous deadline (answers count if they arrived
        before it) and open the next; a cycle whose work ends after the next
        deadline is a deadline miss.
        """
        cell = self.cell
        lockstep = self.config.clock == "lockstep"
        timing = LoopTiming(cell.cycle_ns)
        timer = None if lockstep else AbsoluteDeadlineTimer(cell.cycle_ns)
        # with nothing to stop on (a hold run), reaching max_cycles is the plan, not a timeout
        ep = dict(first_seq=cell.fri.seq + 1, peak=0.0, missed_answers=0,
                  reason="timeout" if stop_on or n is not None else "elapsed", k=0,
                  answer=Histogram(), closed_loop=Histogram(), sent={}, last_estimate=-1, goal_at=-1.0,
                  run=0, miss_run=0, sec=Sections(*SECTIONS))
        fri0 = cell.fri.statistics()  # the link's counters run for its whole session: report this episode's
        wall0, wall0_ns = time.monotonic(), now_ns()  # CLOCK_MONOTONIC: benches line other loops up with it
        stall_every = int(self.config.stall_every_s * 1000) if self.config.stall_ms > 0 else 0
        open_cycle = None
        while ep["k"] < max_cycles:
            if self.svc.stop.is_set():
                ep["reason"] = "stopped"
                break
            ep["sec"].cycles += 1
            if lockstep:
                t0 = now_ns()
                m, sent = self._open(ep)
                needed = [w for w in wait_for if w != "phase" or m.stamp_ns % 10_000_000 == 0]
                t_wait = now_ns()
                if needed and not self._wait_for(needed, m.seq):
                    ep["missed_answers"] += 1
                ep["sec"].add("wait", now_ns() - t_wait)
                done = self._close(m, sent, lockstep, ep, stop_on)
                timing.record(0, now_ns() - t0, missed=False)
            else:
                t_wait = now_ns()
                deadline, wake = timer.wait()
                t0 = now_ns()
                ep["sec"].add("wait", t0 - t_wait)
                done = self._close(*open_cycle, lockstep, ep, stop_on) if open_cycle is not None else None
                if stall_every and ep["k"] > 0 and ep["k"] % stall_every == 0:
                    time.sleep(self.config.stall_ms / 1e3)  # injected fault: the loop stalls
                open_cycle = None if done else self._open(ep)
                t_end = now_ns()
                timing.record(wake - deadline, t_end - t0, missed=t_end > deadline + cell.cycle_ns)
            if done:
                break
            if n is not None and ep["k"] >= n:
                ep["reason"] = "settled"
                break
            if ep["k"] % 100 == 0 and self._stop_requested():
                ep["reason"] = "stopped"
                break
        if open_cycle is not None:
            self._close(*open_cycle, lockstep, ep, None)  # do not leave a measured cycle unapplied
        stats = cell.fri.statistics()
        return dict(
            seq=cell.fri.seq, stamp_ns=cell.t_ns, sent_ns=now_ns(), episode=self.episode, kind=self.kind,
            reason=ep["reason"], first_seq=ep["first_seq"], last_seq=cell.fri.seq,
            sim_seconds=ep["k"] * cell.cycle_ns / 1e9, wall_seconds=time.monotonic() - wall0,
            final_position=cell.sim.tcp_position(), peak_contact_force=ep["peak"], safety=int(cell.krc.safety),
            missed_answers=ep["missed_answers"], goal_reached_at_s=ep["goal_at"],
            fri={"answered": stats.answered - fri0.answered, "missed": stats.missed - fri0.missed,
                 "late": stats.late - fri0.late, "corrupt": stats.corrupt - fri0.corrupt,
                 "longest_miss_run": ep["miss_run"], "state": int(stats.state), "quality": int(stats.quality)},
            loop=dict(timing.summary(), clock=self.config.clock, sched_fifo=self.fifo,
                      answer_latency=ep["answer"].to_dict(), closed_loop_latency=ep["closed_loop"].to_dict(),
                      sections=ep["sec"].summary(), wall_start_ns=wall0_ns, wall_end_ns=now_ns()),
        )

    def _open(self, ep):
        """Measure and publish: the FRI measurement and the physics' truth."""
        cell, sec = self.cell, ep["sec"]
        t0 = now_ns()
        m = cell.begin_cycle()
        sent = now_ns()
        sec.add("measure", sent - t0)
        state = ROBOT_STATE.encode(
            seq=m.seq, stamp_ns=m.stamp_ns, sent_ns=sent, reflected_seq=m.reflected_seq,
            fri_state=int(m.state), fri_quality=int(m.quality), control_mode=int(m.control_mode),
            msr_jnt_pos=m.msr_jnt_pos, msr_cart_pos=m.msr_cart_pos, est_ext_tcp_ft=m.est_ext_tcp_ft,
            answer_rate=m.answer_rate, latency_s=m.latency_s, jitter_s=m.jitter_s, miss_rate=m.miss_rate,
            safety=int(cell.krc.safety), gravity_compensation=bool(cell.krc.gravity_compensation),
            episode=self.episode)
        t1 = now_ns()
        self._pub_state.put(state)
        t2 = now_ns()
        sec.add("encode", t1 - sent)
        sec.add("publish", t2 - t1)
        wrench, contact, touching = cell.tool_wrench, cell.contact_force, cell.touching
        true_phase = self.labeler.update(touching)
        ep["peak"] = max(ep["peak"], float(np.linalg.norm(contact)))
        ep["sent"][m.seq] = sent
        if len(ep["sent"]) > 2000:  # the closed loop spans a few cycles: forget the old ones
            for old in [k for k in ep["sent"] if k < m.seq - 1000]:
                del ep["sent"][old]
        t3 = now_ns()
        contact_msg = ROBOT_CONTACT.encode(
            seq=m.seq, stamp_ns=m.stamp_ns, sent_ns=t3, wrench=wrench, contact_force=contact,
            touching=touching, true_phase=true_phase, episode=self.episode)
        t4 = now_ns()
        self._pub_contact.put(contact_msg)
        sec.add("measure", t3 - t2)
        sec.add("encode", t4 - t3)
        sec.add("publish", now_ns() - t4)
        return m, sent

    def _close(self, m, sent, lockstep, ep, stop_on) -> bool:
        """Hand this cycle's answers to the FRI link, apply the hand, step.
        Returns True when the episode should end."""
        cell, sec = self.cell, ep["sec"]
        t0 = now_ns()
        with self._cond:
            # every answer that came since the last close: this cycle's, and late ones
            # for cycles already closed, which the FRI link must see to count them late
            commands = self._answers["command"]
            cmd_entries = sorted(commands.items()) if commands else ()
            commands.clear()
            teacher_entry = self._answers["teacher"].pop(m.seq, None)
            latest_teacher = self._latest_teacher
        goal_reached = teacher_done = False
        for seq, (msg, recv) in cmd_entries:
            sent_at = sent if seq == m.seq else ep["sent"].get(seq)
            if sent_at is None:  # an answer to a cycle of no episode of ours
                continue
            ep["answer"].add(recv - sent_at)
            est = msg.get("estimate_seq", -1)
            if est > ep["last_estimate"] and est in ep["sent"]:
                # closed loop: this cycle's measurement -> sensor -> estimator -> commander -> here
                ep["closed_loop"].add(recv - ep["sent"][est])
                ep["last_estimate"] = est
            stamp = m.stamp_ns - (m.seq - seq) * cell.cycle_ns
            arrival = stamp + (LOCKSTEP_LATENCY_NS if lockstep else recv - sent_at)
            cell.receive(CommandPacket(seq=msg["seq"], cart_pos=np.array(msg["cart_pos"]),
                                       cart_stiffness=np.array(msg["cart_stiffness"]),
                                       cart_damping=np.array(msg["cart_damping"]),
                                       add_tcp_ft=np.array(msg["add_tcp_ft"]),
                                       requested_mode=ControlMode(msg["requested_mode"])), arrival)
            if seq == m.seq:
                goal_reached = bool(msg["goal_reached"])
                if goal_reached and ep["goal_at"] < 0:
                    ep["goal_at"] = ep["k"] * cell.cycle_ns / 1e9
        teacher_msg = teacher_entry[0] if teacher_entry is not None else (None if lockstep else latest_teacher)
        hand = None
        # episode indices count demonstrations and reproductions separately: the teacher
        # still set up for demonstration 5 answered reproduction 5 and pushed the arm
        if teacher_msg is not None and teacher_msg["episode"] == self.episode and self.kind == "demonstration":
            hand = np.array(teacher_msg["wrench"])
            teacher_done = bool(teacher_msg["done"])
        t1 = now_ns()
        outcome = cell.end_cycle(hand).outcome
        sec.add("answers", t1 - t0)
        sec.add("step", now_ns() - t1)
        ep["k"] += 1
        ep["run"] = 0 if outcome.answered else ep["run"] + 1
        ep["miss_run"] = max(ep["miss_run"], ep["run"])
        fri = cell.fri
        if self.kind == "reproduction" and fri.state == FriState.MON and not fri.command_requested:
            # as the KRL program of a lab set-up does: after a fall-back to monitor
            # mode, ask for command mode again (entered once the link is PERFECT again)
            fri.request_command_mode()
        for flag, name in ((teacher_done, "teacher_done"), (goal_reached, "goal_reached")):
            if flag and stop_on == name:
                ep["reason"] = name
                return True
        if cell.krc.safety != 0:
            ep["reason"] = f"safety:{SafetyReason(cell.krc.safety).name.lower()}"
            return True
        return False


def main(config: RobotConfig) -> int:
    with Service("robot", config.run_id, config.zenoh, sched_fifo=config.sched_fifo,
                 cpus=config.cpus) as svc:
        robot = RobotProcess(config, svc)
        svc.log(f"ready: world {config.world}, clock {config.clock}, SCHED_FIFO {'on' if robot.fifo else 'off'}")
        robot.serve()
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="etar-robot", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-id", required=True, help="run id: topics live under etar/<run-id>/")
    parser.add_argument("--clock", choices=("lockstep", "realtime"), default="lockstep")
    parser.add_argument("--world", choices=sorted(WORLDS), default="valley")
    parser.add_argument("--seed", type=int, default=0, help="seed of the F/T model inside the cell")
    parser.add_argument("--answer-timeout", type=float, default=5.0,
                        help="lockstep: seconds to wait for a cycle's answers before counting a miss")
    add_sched_fifo_argument(parser)
    parser.add_argument("--stall-every", type=float, default=0.0, help="fault injection: stall every N s")
    parser.add_argument("--stall-ms", type=float, default=0.0, help="fault injection: stall length, ms")
    add_zenoh_arguments(parser)
    return parser


def cli(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return main(RobotConfig(run_id=args.run_id, zenoh=zenoh_options(args), clock=args.clock, world=args.world,
                            seed=args.seed, answer_timeout_s=args.answer_timeout, sched_fifo=args.sched_fifo,
                            cpus=args.cpus,
                            stall_every_s=args.stall_every, stall_ms=args.stall_ms))


if __name__ == "__main__":
    sys.exit(cli())
