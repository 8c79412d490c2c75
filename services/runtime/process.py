"""One node in its own process on a Zenoh session: the entry point every service shares.

``services.<role>`` is a thin shell: ``node_process(role)`` gives it
``build_parser``, ``main`` and ``cli``.  The flags common to every service
(``--run-id``, ``--clock``, the Zenoh flags, ``--sched-fifo``, ``--cpus``) are
defined here once, the node's own come from its config dataclass
(``services.runtime.config``).  ``main`` opens the session
(``services.runtime.service.Service``), builds the node with a bus that
publishes on it, hands the node its subscriptions and serves control requests
until ``shutdown`` or a signal.

What only a network needs lives here too: the robot's episodes run the cycle
engine (``services.runtime.cycle``) on the wall clock, waking for each answer
that arrives and at each deadline or answer timeout; the recorder's
``end_episode`` first waits (bounded) for messages still in flight.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass

import zenoh

from services.nodes import NODES
from services.runtime.bus import MonotonicClock
from services.runtime.collector import PausedCollector
from services.runtime.config import add_config_arguments, config_from_args
from services.runtime.cycle import CycleEngine
from services.runtime.service import Service
from services.runtime.session import ZenohOptions, add_zenoh_arguments, zenoh_options, zenoh_reason

CLOCKS = ("lockstep", "realtime")
RECORDER_WAIT_S = 10.0  # end_episode: how long the recorder waits for messages still in flight
STOP_CHECK_NS = 100_000_000  # during an episode the robot looks for a 'stop' at least this often
PROGRAMS = {"robot": "etar-robot", "ft_sensor": "etar-ft-sensor", "teacher": "etar-teacher",
            "phase_estimator": "etar-phase-estimator", "impedance_commander": "etar-impedance-commander",
            "recorder": "etar-recorder", "foxglove_bridge": "etar-foxglove-bridge"}


@dataclass(frozen=True)
class ProcessConfig:
    """What every service process takes besides its node's config."""

    run_id: str
    zenoh: ZenohOptions
    clock: str = "lockstep"
    sched_fifo: int = 0  # SCHED_FIFO priority for the whole process, 0: none
    cpus: tuple = ()  # CPU affinity of the whole process, (): any


class ZenohBus:
    """Publishes a node's messages on its service's Zenoh publishers."""

    def __init__(self, svc: Service, realtime: bool):
        self.svc = svc
        self.realtime = realtime
        self._pubs = {}

    def declare(self, publications) -> None:
        for p in publications:
            self._pubs[p.topic] = self.svc.publisher(p.topic, realtime=p.express,
                                                     drop_when_congested=p.drop_when_congested and self.realtime)

    def publish(self, topic: str, payload: bytes, message=None) -> None:
        self._pubs[topic].put(payload)


def run_node(role: str, node_config, process: ProcessConfig) -> int:
    node_cls, _ = NODES[role]
    if process.clock not in CLOCKS:
        raise ValueError(f"clock must be lockstep or realtime, got {process.clock!r}")
    realtime = process.clock == "realtime"
    clock = MonotonicClock()
    with Service(role, process.run_id, process.zenoh, sched_fifo=process.sched_fifo, cpus=process.cpus) as svc:
        bus = ZenohBus(svc, realtime)
        node = node_cls(node_config, bus, clock, run_id=process.run_id, mode=process.clock,
                        sched_fifo=svc.sched_fifo)
        bus.declare(node.publications)
        collector = PausedCollector()
        inputs = NodeInputs(node, svc, realtime, collector)
        inputs.sync()
        handlers = {cmd: inputs.after(h) for cmd, h in node.handlers().items()}
        if role == "robot":
            handlers.update(_robot_handlers(node, svc, node_config, process.clock, clock, collector))
        if role == "recorder":
            handlers["end_episode"] = _recorder_end(node)

        def idle():
            collector.relieve()
            node.idle(clock.now_ns())

        if realtime:
            collector.start()
        svc.log(f"ready: clock {process.clock}, SCHED_FIFO {'on' if svc.sched_fifo else 'off'}")
        try:
            svc.serve(handlers, status=lambda: dict(node.status(), sched_fifo=svc.sched_fifo,
                                                    cpus=sorted(os.sched_getaffinity(0)),
                                                    gc_relieved=collector.relieved),
                      idle=idle)
        finally:
            collector.stop()
            node.close()
    return 0


class NodeInputs:
    """A node's subscriptions on its service.  In realtime they are declared only while
    the node is ``listening``, re-read after every control request: Zenoh then stops
    delivering what the node would ignore (a declaration takes a moment to reach the
    publishers, which lockstep, where every message counts, cannot allow: there they
    stay declared)."""

    def __init__(self, node, svc: Service, realtime: bool, collector: PausedCollector | None = None):
        self.node, self.svc, self.realtime = node, svc, realtime
        self.collector = collector
        self.declared = []

    def sync(self) -> None:
        want = self.node.listening or not self.realtime
        if want and not self.declared:
            self.declared = [self.svc.subscribe(s.topic, s.handler, decode=s.decode, every_tenth=s.every_tenth,
                                                latest=s.latest and self.realtime, keep_tenth=s.keep_tenth)
                             for s in self.node.subscriptions]
        elif not want and self.declared:
            for s in self.declared:
                self.svc.unsubscribe(s)
            self.declared = []

    def after(self, handler):
        """``handler``, followed by ``sync``."""
        def handled(*args):
            try:
                return handler(*args)
            finally:
                self.sync()
                if self.collector is not None:
                    self.collector.between_episodes()  # a control request: between episodes
        handled.replies_itself = getattr(handler, "replies_itself", False)
        return handled


# ------------------------------------------------------------------ the robot's episodes

def _robot_handlers(node, svc: Service, config, mode: str, clock, collector: PausedCollector) -> dict:
    def settle(p):
        try:
            return drive_episode(node, svc, node.plan("settle", p), mode, clock, config, settle=True,
                                 collector=collector)
        finally:
            collector.between_episodes()

    def run(p, reply):
        plan = node.plan("run", p)  # a bad request fails before the episode starts
        reply(started=True, seq=node.cell.fri.seq + 1)
        try:
            summary = drive_episode(node, svc, plan, mode, clock, config, collector=collector)
            node.publish_summary(summary)
        finally:
            collector.between_episodes()

    return {"settle": settle, "run": _answered_first(run),
            "stop": lambda p: {"stopped": False, "note": "no episode is running"}}


def _answered_first(fn):
    """A handler that replies before it returns (``run``: the episode goes on after the reply)."""
    fn.replies_itself = True
    return fn


def drive_episode(node, svc: Service, plan, mode: str, clock, config, settle: bool = False,
                  collector: PausedCollector | None = None) -> dict:
    """Run one episode of cycles on the wall clock; returns its summary."""
    node.begin_episode(settle)
    engine = CycleEngine(node, plan, clock, mode=mode, cycle_ns=node.cell.cycle_ns,
                         answer_timeout_ns=int(config.answer_timeout * 1e9),
                         stall_every_cycles=int(config.stall_every * 1000) if config.stall_ms > 0 else 0,
                         stall_s=config.stall_ms / 1e3)
    lockstep = mode == "lockstep"
    checked, checked_at = 0, clock.now_ns()
    arrived = node.arrived
    seen = node.arrivals
    while not engine.done:
        if svc.stop.is_set():
            engine.stop()
            break
        now = clock.now_ns()
        wake = engine.tick(now)
        if engine.done:
            break
        # during an episode only 'stop' and 'status' are served: every 100 cycles, and at
        # least every 100 ms (a lockstep cycle waiting for a dead participant is slow)
        if engine.k >= checked + 100 or now - checked_at > STOP_CHECK_NS:
            checked, checked_at = engine.k, now
            if collector is not None:
                collector.relieve()
            if _stop_requested(node, svc):
                engine.stop()
                break
        if lockstep and not engine.awaiting():
            continue  # the open cycle has all it needs (or needs nothing): close it now
        with arrived:
            if node.arrivals == seen:
                left = (wake - clock.now_ns()) / 1e9
                if left > 0:
                    # lockstep: also wake every 50 ms to notice a stop
                    arrived.wait(min(left, 0.05) if lockstep else left)
            seen = node.arrivals
    return node.end_episode(engine)


def _stop_requested(node, svc: Service) -> bool:
    req = svc.next_control()
    if req is None:
        return False
    if req.cmd == "stop":
        req.reply(stopped=True)
        return True
    if req.cmd == "status":
        req.reply(**node.status(), running=True)
    else:
        req.fail(f"busy running episode {node.episode}: only 'stop' and 'status' are served now")
    return False


# ------------------------------------------------------------------ the recorder's episodes

def _recorder_end(node):
    def end(p):
        wanted, last = list(p.get("topics", [])), int(p.get("last_seq", -1))
        deadline = time.monotonic() + float(p.get("timeout", RECORDER_WAIT_S))
        with node.lock:
            while node.lagging(wanted, last) and time.monotonic() < deadline:
                node.lock.wait(0.05)
        return node.end(p)
    return end


# ------------------------------------------------------------------ the entry point

def node_process(role: str):
    """``(build_parser, main, cli)`` for the service process of ``role``; its help is the node's documentation."""
    node_cls, config_cls = NODES[role]
    doc = sys.modules[node_cls.__module__].__doc__

    def build_parser() -> argparse.ArgumentParser:
        parser = argparse.ArgumentParser(prog=PROGRAMS[role], description=doc,
                                         formatter_class=argparse.RawDescriptionHelpFormatter)
        parser.add_argument("--run-id", required=True, help="run id: topics live under etar/<run-id>/")
        parser.add_argument("--clock", choices=CLOCKS, default="lockstep",
                            help="lockstep: every cycle waits for its answers (deterministic); "
                                 "realtime: 1 ms wall-clock deadlines (default lockstep)")
        add_config_arguments(parser.add_argument_group(role.replace("_", " ")), config_cls)
        add_zenoh_arguments(parser)
        return parser

    def main(node_config, process: ProcessConfig) -> int:
        return run_node(role, node_config, process)

    def cli(argv=None) -> int:
        args = build_parser().parse_args(argv)
        try:
            node_config = config_from_args(config_cls, args)
            process = ProcessConfig(run_id=args.run_id, zenoh=zenoh_options(args), clock=args.clock,
                                    sched_fifo=args.sched_fifo, cpus=args.cpus)
            return main(node_config, process)
        except (ValueError, OSError) as exc:
            print(f"{PROGRAMS[role]}: error: {exc}", file=sys.stderr)
            return 2
        except zenoh.ZError as exc:  # e.g. an endpoint it cannot listen on
            print(f"{PROGRAMS[role]}: error: zenoh: {zenoh_reason(exc)}", file=sys.stderr)
            return 2

    return build_parser, main, cli
