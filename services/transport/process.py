"""One node in its own process on a Zenoh session (``services.cli.roles`` parses its flags).

``run_node`` opens the session (``services.transport.service.Service``), builds the
node with a bus that publishes on it, hands the node its subscriptions and serves
control requests until ``shutdown`` or a signal.

What only a network needs lives here too: the robot's episodes run the cycle
engine (``services.runtime.cycle``) on the wall clock, waking for each answer
that arrives and at each deadline or answer timeout; the recorder's
``end_episode`` first waits (bounded) for messages still in flight.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass

import zenoh

from robot_sim.cycle import FRI_RATE_HZ
from services.nodes import NODES
from services.runtime import topics
from services.runtime.bus import MonotonicClock
from services.runtime.cycle import CLOCKS, CycleEngine
from services.runtime.roles import PARTICIPANTS, ROLES
from services.transport.collector import PausedCollector
from services.transport.lab import edges
from services.transport.service import Service
from services.transport.session import ZenohOptions

RECORDER_WAIT_S = 10.0  # end_episode: how long the recorder waits for messages still in flight
STOP_CHECK_NS = 100_000_000  # during an episode the robot looks for a 'stop' at least this often


@dataclass(frozen=True)
class ProcessConfig:
    """What every service process takes besides its node's config."""

    run_id: str
    zenoh: ZenohOptions
    clock: str = "lockstep"
    sched_fifo: int = 0  # SCHED_FIFO priority for the whole process (1..99), 0: none
    cpus: tuple = ()  # CPU affinity of the whole process, (): any

    def __post_init__(self):
        if self.sched_fifo is not True and not 0 <= int(self.sched_fifo) <= 99:
            raise ValueError(f"--sched-fifo {self.sched_fifo}: a SCHED_FIFO priority is 1..99 (0: off)")


def fifo_refusal(priority: int) -> str | None:
    """Switch this process to SCHED_FIFO at ``priority``: None if granted, else why not, in
    the system's words (e.g. "Operation not permitted": root, CAP_SYS_NICE or an rtprio
    limit is needed).  The service applies the policy again before its session opens (a
    no-op once granted): this says why it could not."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except AttributeError:
        return "SCHED_FIFO is not available on this system"
    except OSError as exc:
        return exc.strerror or str(exc)
    return None


def fifo_words(requested, granted, refusal: str | None) -> str:
    """The ready line's word on SCHED_FIFO: off, the priority in use, or why it was not granted."""
    if not requested:
        return "SCHED_FIFO off"
    if granted:
        return f"SCHED_FIFO {granted}"
    priority = 50 if requested is True else int(requested)
    return f"SCHED_FIFO {priority} not granted: {refusal or 'refused'}"


class ZenohBus:
    """Publishes a node's messages on its service's Zenoh publishers.  Only the bytes
    cross: a node need not make the dict beside them (``carries_dicts``)."""

    carries_dicts = False

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
    refusal = fifo_refusal(50 if process.sched_fifo is True else int(process.sched_fifo)) if process.sched_fifo \
        else None
    with Service(role, process.run_id, process.zenoh, sched_fifo=process.sched_fifo, cpus=process.cpus) as svc:
        bus = ZenohBus(svc, realtime)
        node = node_cls(node_config, bus, clock, run_id=process.run_id, mode=process.clock,
                        sched_fifo=svc.sched_fifo, **edges(role, node_config, clock, svc.session))
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
        svc.log(f"ready: clock {process.clock}, {fifo_words(process.sched_fifo, svc.sched_fifo, refusal)}")
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
    delivering what the node would ignore.  In lockstep, where every message counts, a
    declaration that reaches a publisher after its first message of an episode loses that
    message, so there they stay declared; but for a role that subscribes when listening
    (``roles.Role.subscribes_when_listening``, the teacher): it declares them for an
    episode and then a liveliness token saying so (``topics.listening``), which the robot
    waits for before the episode's first cycle (``Listeners``).  Zenoh sends a session's
    declarations in order on each link, so a publisher that has seen the token routes to
    the subscriptions: 0 first messages lost in 1 000 such handshakes here, against 3 in
    300 when the word that a subscriber was ready came through a third process
    (docs/benchmarks.md)."""

    def __init__(self, node, svc: Service, realtime: bool, collector: PausedCollector | None = None):
        self.node, self.svc, self.realtime = node, svc, realtime
        self.collector = collector
        self.declared = []
        self.on_demand = node.name in ROLES and ROLES[node.name].subscribes_when_listening
        self._token = self._token_key = self._token_for = None
        self._tokens = 0

    def sync(self) -> None:
        want = self.node.listening or not (self.realtime or self.on_demand)
        if want and not self.declared:
            self.declared = [self.svc.subscribe(s.topic, s.handler, decode=s.decode, every_tenth=s.every_tenth,
                                                latest=s.latest and self.realtime, keep_tenth=s.keep_tenth,
                                                horizon=s.horizon)
                             for s in self.node.subscriptions]
        elif not want and self.declared:
            for s in self.declared:
                self.svc.unsubscribe(s)
            self.declared = []
        if self.on_demand:
            episode = self.node.episode if want else None
            if episode != self._token_for:
                if self._token is not None:
                    self._token.undeclare()
                self._token = self._token_key = None
                if episode is not None:
                    # after the subscriptions: the token must not reach anyone before they do;
                    # a fresh key each time, so that one from before an idle (the same episode
                    # reset again) never passes for this one while its end is still in transit
                    self._tokens += 1
                    self._token_key = topics.listening(self.svc.run_id, self.node.name, f"{episode}.{self._tokens}")
                    self._token = self.svc.session.liveliness().declare_token(self._token_key)
                self._token_for = episode

    def after(self, handler):
        """``handler``, followed by ``sync``; its reply also carries ``listening``, the token
        to wait for, when the node subscribes on demand and now listens."""
        def handled(*args):
            try:
                reply = handler(*args)
            finally:
                self.sync()
                if self.collector is not None:
                    self.collector.between_episodes()  # a control request: between episodes
            if self._token_key is not None and not handled.replies_itself:
                reply = dict(reply or {}, listening=self._token_key)
            return reply
        handled.replies_itself = getattr(handler, "replies_itself", False)
        return handled


# ------------------------------------------------------------------ the robot's episodes

class Listeners:
    """The listening tokens (``topics.listening``) of the run's services, as this
    process's session has them: a role that subscribes only while it listens has its
    subscriptions here once its token is (``NodeInputs``)."""

    def __init__(self, svc: Service):
        self._live: set = set()
        self._changed = threading.Condition()
        self._sub = svc.session.liveliness().declare_subscriber(topics.listening(svc.run_id, "*", "*"), self._on,
                                                                  history=True)

    def _on(self, sample) -> None:
        with self._changed:
            if sample.kind == zenoh.SampleKind.PUT:
                self._live.add(str(sample.key_expr))
            else:
                self._live.discard(str(sample.key_expr))
            self._changed.notify_all()

    def _has(self, key: str) -> bool:
        if key.endswith("*"):  # any token under this prefix
            return any(live.startswith(key[:-1]) for live in self._live)
        return key in self._live

    def wait(self, keys, timeout: float) -> list:
        """Until every token in ``keys`` is live (one ending in ``*``: any token so
        beginning), ``timeout`` at most; the ones still missing."""
        with self._changed:
            self._changed.wait_for(lambda: all(self._has(k) for k in keys), timeout)
            return [k for k in keys if not self._has(k)]


LISTENING_TIMEOUT_S = 10.0  # a role reset for an episode says it listens within milliseconds


def _robot_handlers(node, svc: Service, config, mode: str, clock, collector: PausedCollector) -> dict:
    listeners = Listeners(svc) if mode == "lockstep" else None
    def settle(p):
        try:
            return drive_episode(node, svc, node.plan("settle", p), mode, clock, config, settle=True,
                                 collector=collector)
        finally:
            collector.between_episodes()

    def run(p, reply):
        plan = node.plan("run", p)  # a bad request fails before the episode starts
        keys = p.get("listening") or []
        if not (isinstance(keys, list) and all(isinstance(k, str) for k in keys)):
            raise ValueError(f"listening must be a list of token keys, got {keys!r}")
        if listeners is not None:
            # the episode's first messages must reach the roles that subscribe only when they
            # listen: the tokens their resets replied (a runner that does not pass them: any
            # token of theirs for this episode)
            roles = [r for r in (PARTICIPANTS[a] for a in plan.answers_from) if ROLES[r].subscribes_when_listening]
            keys = keys or [topics.listening(svc.run_id, r, f"{node.episode}.*") for r in roles]
            missing = listeners.wait(keys, LISTENING_TIMEOUT_S)
            if missing:
                raise ValueError(f"not listening for episode {node.episode} after {LISTENING_TIMEOUT_S:.0f} s "
                                 f"(no token {', '.join(missing)}): was it reset for this episode?")
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
                         stall_every_cycles=int(config.stall_every * FRI_RATE_HZ) if config.stall_ms > 0 else 0,
                         stall_s=config.stall_ms / 1e3)
    lockstep = mode == "lockstep"
    node.inbox.awaited = frozenset(plan.answers_from)
    checked, checked_at = 0, clock.now_ns()
    arrived = node.inbox.arrived
    seen = node.inbox.arrivals
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
            if node.inbox.arrivals == seen:
                left = (wake - clock.now_ns()) / 1e9
                if left > 0:
                    # lockstep: also wake every 50 ms to notice a stop
                    arrived.wait(min(left, 0.05) if lockstep else left)
            seen = node.inbox.arrivals
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
