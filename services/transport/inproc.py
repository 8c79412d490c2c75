"""Every node of a run in one process, on an in-memory bus, in lockstep.

``InProcessBus.publish`` queues a message; ``drain`` delivers the queue in
order, first in first out, to every subscriber of its topic, each message
decoded once for all of them with the same decoder and the same checks as a
Zenoh subscriber (``services.runtime.messages``), and the same every-tenth
filter on the raw bytes.  What a network needs and one process does not is
skipped: no session, no sockets, no per-process threads; messages are still
encoded, because the encoded bytes are what the recorder writes.

``InProcessCell`` is the runner's side: the nodes of a run built from their
configs, control requests as calls, and an episode driven by the same cycle
engine as over Zenoh (``services.runtime.cycle``): open a cycle, deliver
everything it caused, close it once its answers are in.  When everything has
been delivered and a cycle still waits, nothing more can come: the nodes are
told (``Node.quiescent``: the commander goes on without an estimate that will not
come, as it does after ``ESTIMATE_WAIT_S`` over Zenoh) and then the cycle closes
with a missed answer, as after the answer timeout over Zenoh.  So the same seed
records the same messages either way (tests/e2e/test_scenarios.py).
"""

from __future__ import annotations

import os
from collections import deque

from services.nodes import NODES
from services.runtime.bus import MonotonicClock
from services.runtime.cycle import CycleEngine
from services.runtime.messages import BY_TOPIC, EPISODE_SUMMARY, MessageError, estimator_instant
from services.transport.lab import edges
from services.transport.subscriptions import tenth_cycle

_UNDECODED = object()
PROGRESS_CYCLES = 500  # how often an episode tells its progress (simulated 0.5 s)


def _tenth_stamp(message: dict) -> bool:
    """``tenth_cycle`` of a message packed in this process, from its stamp instead of its bytes."""
    stamp = message["stamp_ns"]
    return stamp < 0 or estimator_instant(stamp)


def _same(a, b) -> bool:
    """Equal, and of the same types all the way down (1 and 1.0 are not the same here)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


class InProcessBus:
    """``check``: verify that every message handed over in memory is exactly what
    decoding its bytes gives (the tests run with it; ETAR_INPROC_CHECK=1 turns it on)."""

    carries_dicts = True  # a subscriber in this process takes the publisher's dict

    def __init__(self, clock=None, check: bool | None = None):
        self.clock = clock or MonotonicClock()
        self.check = bool(int(os.environ.get("ETAR_INPROC_CHECK", "0"))) if check is None else check
        self._queue: deque = deque()
        self._subs: dict[str, list] = {}
        self._all: list = []
        self.bad: dict[tuple, int] = {}  # (node, topic) -> messages that did not decode or whose handler raised
        self.last_error: dict[tuple, str] = {}
        self._decode_error = ""

    def attach(self, node) -> None:
        for sub in node.subscriptions:
            if sub.topic == "**":
                self._all.append((node.name, sub))
            else:
                self._subs.setdefault(sub.topic, []).append((node.name, sub))

    def publish(self, topic: str, payload: bytes, message: dict | None = None) -> None:
        if self.check and message is not None:
            self.verify(topic, payload, message)
        self._queue.append((topic, payload, message))

    def verify(self, topic: str, payload: bytes, message: dict) -> None:
        """AssertionError unless ``message`` is exactly what ``payload`` decodes to."""
        decoded = self._decode(topic, payload)
        if not _same(decoded, message):
            raise AssertionError(f"{topic}: the message handed over in memory is not what its bytes decode to:"
                                 f"\n  in memory {message!r}\n  decoded   {decoded!r}")

    def pending(self) -> bool:
        return bool(self._queue)

    def drain(self) -> None:
        queue, subs, now = self._queue, self._subs, self.clock.now_ns
        while queue:
            topic, raw, message = queue.popleft()
            self.deliver_to(subs, topic, raw, message, now())

    def deliver_to(self, subs: dict, topic: str, raw: bytes, message: dict | None, recv: int) -> None:
        """One message to the subscriptions of ``subs`` (topic -> [(node name, Subscription)],
        '**' for every topic) and to this bus's wildcard subscribers."""
        # decoding is what a network needs: a message packed in this process is handed over as it is
        msg = _UNDECODED if message is None else message
        for name, sub in subs.get(topic, ()):
            if sub.every_tenth and not (tenth_cycle(raw) if message is None else _tenth_stamp(message)):
                continue
            if sub.decode:
                if msg is _UNDECODED:
                    msg = self._decode(topic, raw)
                if msg is None:
                    self.count_bad(name, topic, self._decode_error)
                    continue
                arg = msg
            else:
                arg = None
            try:
                sub.handler(arg, recv, raw)
            except Exception as exc:  # a bad message must not stop the run
                self.count_bad(name, topic, f"{type(exc).__name__}: {exc}")
        for name, sub in (self._all if subs is self._subs else subs.get("**", ())):
            sub.handler(topic, recv, raw, message)

    def _decode(self, topic, raw):
        mtype = BY_TOPIC.get(topic)
        if mtype is None:
            self._decode_error = f"no message type for topic {topic!r}"
            return None
        try:
            return mtype.decode(raw)
        except MessageError as exc:
            self._decode_error = str(exc)
            return None

    def count_bad(self, name, topic, error):
        key = (name, topic)
        self.bad[key] = self.bad.get(key, 0) + 1
        self.last_error[key] = error

    def links(self, name: str) -> dict:
        return {topic: {"bad": n, "last_error": self.last_error.get((node, topic), "")}
                for (node, topic), n in self.bad.items() if node == name}


class InProcessCell:
    """The nodes of one run in this process (a ``services.transport.cell.Cell``).
    ``configs``: role -> node config."""

    restarts = ()  # nothing restarts in one process

    def __init__(self, run_id: str, configs: dict, clock=None):
        self.clock = clock or MonotonicClock()
        self.run_id = run_id
        self.bus = InProcessBus(self.clock)
        self.nodes = {}
        self._progress = None  # run_episode's progress callback, for the cycles of that episode
        try:
            for role, config in configs.items():
                node_cls, _ = NODES[role]
                node = node_cls(config, self.bus, self.clock, run_id=run_id, mode="lockstep",
                                **edges(role, config, self.clock))
                self.nodes[role] = node
                self.bus.attach(node)
        except BaseException:
            self.close()  # the nodes built so far (the recorder's writer process among them)
            raise

    def request(self, role: str, cmd: str, timeout: float | None = None, **args) -> dict:
        """A control request, answered as a service over Zenoh would answer it; raises
        RuntimeError('<role> refused ...') where a service would reply with an error."""
        node = self.nodes.get(role)
        if node is None:
            raise RuntimeError(f"{role} is not part of this run ({', '.join(self.nodes)})")
        if cmd == "status":
            return dict(ok=True, **node.status(), links=self.bus.links(role))
        if cmd == "shutdown":
            return {"ok": True}
        try:
            if role == "robot" and cmd in ("settle", "run"):
                reply = self._cycles(node, cmd, args)
            else:
                handler = node.handlers().get(cmd)
                if handler is None:
                    raise KeyError(f"unknown command {cmd!r} ({', '.join(sorted(node.handlers()))})")
                reply = handler(args) or {}
        except (KeyError, ValueError, TypeError, OSError) as exc:
            raise RuntimeError(f"{role} refused '{cmd}': {type(exc).__name__}: {exc}") from None
        self.bus.drain()
        return dict(ok=True, **reply)

    def publish(self, topic: str, payload: bytes) -> None:
        self.bus.publish(topic, payload)
        self.bus.drain()

    def _cycles(self, robot, cmd: str, args: dict) -> dict:
        plan = robot.plan(cmd, args)
        robot.begin_episode(settle=cmd == "settle")
        participant = self._participant(robot)
        engine = CycleEngine(participant, plan, self.clock, mode="lockstep", cycle_ns=robot.cell.cycle_ns,
                             answer_timeout_ns=int(robot.config.answer_timeout * 1e9))
        clock = self.clock
        progress = self._progress if cmd == "run" else None
        next_report = PROGRESS_CYCLES
        while not engine.done:
            if progress is not None and engine.k >= next_report:
                next_report += PROGRESS_CYCLES
                progress(engine.k * robot.cell.cycle_ns / 1e9)
            engine.tick(clock.now_ns())
            self._deliver(engine, participant)
        summary = robot.end_episode(engine)
        if cmd == "run":
            robot.publish_summary(summary)
        # what a runner over Zenoh gets: the summary as it crosses the wire
        return EPISODE_SUMMARY.decode(EPISODE_SUMMARY.encode(**summary))

    def _participant(self, robot):
        """What the cycle engine drives: the robot, its cycles' messages carried by the bus."""
        return robot

    def _deliver(self, engine, participant) -> None:
        """Deliver everything the cycle engine's tick caused; a cycle still waiting then can get
        nothing more: the nodes are told, and if it still waits it closes with a missed answer."""
        bus = self.bus
        bus.drain()
        if engine.awaiting():
            for node in self.nodes.values():
                node.quiescent()
            bus.drain()
            if engine.awaiting():
                engine.tick(self.clock.now_ns(), quiescent=True)
                bus.drain()

    def run_episode(self, answers_from, stop_on, max_seconds, progress=None, listening=()) -> dict:
        """One episode (the robot's 'run'), driven to its end; its summary.
        ``progress(simulated seconds)`` is called every PROGRESS_CYCLES cycles."""
        self._progress = progress
        try:
            reply = self.request("robot", "run", wait_for=list(answers_from), stop_on=stop_on,
                                 max_seconds=max_seconds)
        finally:
            self._progress = None
        reply.pop("ok", None)
        return reply

    def stop_episode(self, timeout: float = 30.0) -> dict | None:
        """None: an in-process episode runs in the runner's own thread, so whatever
        interrupted ``run_episode`` has already ended it, before its summary."""
        return None

    def start(self) -> None:
        """The nodes were built with the cell: nothing to wait for."""

    def where(self) -> list[dict]:
        return []

    def unresponsive(self, roles) -> list:
        return []  # one process: a node that does not answer is an exception, not silence

    def kill(self) -> int:
        return 0  # no processes

    def statistics(self, roles) -> dict:
        return {role: self.request(role, "status") for role in roles if role in self.nodes}

    def post_mortem(self) -> list[str]:
        return []  # one process: a failure is the exception the runner already reports

    def stop(self, roles=(), before_report: bool = True) -> dict:
        """Finish every node (the recorder's open file); no processes, so no exit codes."""
        if before_report:
            self.close()
        return {}

    def close(self) -> None:
        """Close every node, even after one raised (the first error is raised after all)."""
        first = None
        for node in self.nodes.values():
            try:
                node.close()
            except Exception as exc:  # noqa: BLE001 - re-raised below, once the others are closed
                first = first or exc
        if first is not None:
            raise first
