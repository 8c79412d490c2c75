"""What every service process shares: a Zenoh session under the run prefix, a
liveliness token, a control queryable, publishers and decoding subscribers,
and a clean stop on SIGINT/SIGTERM.

Control requests are JSON objects ``{"cmd": ..., ...}`` sent with a Zenoh
``get`` to ``etar/<run_id>/<service>/control``; the service answers
``{"ok": true, ...}`` or ``{"ok": false, "error": ...}`` from its own thread
(``next_control``), so control never races the service's loop.
"""

from __future__ import annotations

import json
import queue
import re
import signal
import sys
import threading
import time
from dataclasses import dataclass, field

import zenoh

from services.runtime import topics
from services.runtime.messages import (BY_TOPIC, ESTIMATOR_STRIDE, STRIDES, MessageError, MessageType,
                                      estimator_instant)
from services.transport.profiling import ProcessProfile
from services.transport.session import ZenohOptions, open_session
from services.runtime.timing import FRESH, STALE, Histogram, SequenceTracker


# the wildcard subscription (the recorder's) takes what has arrived every BATCH_S, from
# a queue of ~10 s of every message of a run; when full, Zenoh holds further samples
# back (the publishers' congestion control decides what drops)
BATCH_S = 0.005
BATCH_CAPACITY = 50_000
# older messages in a row after which a link takes them as its stream again: a replayed
# copy comes between new ones, the real stream behind a forged far-ahead seq does not
# (50 cycles: FRI command mode drops, and comes back, rather than the link going silent)
RESYNC_AFTER = 50


def now_ns() -> int:
    return time.monotonic_ns()


@dataclass
class LinkCounters:
    """Per subscribed topic, at the receiving end: what arrived, what was garbage,
    one-way latency (publish -> this callback, same-host CLOCK_MONOTONIC) and
    lost / out-of-order messages from the sequence numbers.  ``skipped``: messages
    a ``latest`` subscriber passed over for a newer one (also in ``lost``).
    ``dropped``: duplicates and messages older than one already delivered, which
    are counted (``duplicates``, ``out_of_order``) but not handed to the node;
    ``resyncs``: times ``RESYNC_AFTER`` older messages in a row made the link take
    them as its stream again (the newest had been forged far ahead)."""

    received: int = 0
    bad: int = 0
    skipped: int = 0
    dropped: int = 0
    resyncs: int = 0
    stale_run: int = 0
    last_error: str = ""
    latency: Histogram = field(default_factory=Histogram)
    sequence: SequenceTracker = field(default_factory=SequenceTracker)

    def to_dict(self) -> dict:
        seq = self.sequence.to_dict()
        return {"received": self.received, "bad": self.bad, "skipped": self.skipped, "dropped": self.dropped,
                "resyncs": self.resyncs, "last_error": self.last_error,
                "latency": self.latency.summary(), "lost": seq["lost"], "out_of_order": seq["out_of_order"],
                "duplicates": seq["duplicates"]}


def _plain(value):
    """JSON for numpy arrays and scalars in control replies."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


class ControlRequest:
    def __init__(self, query: zenoh.Query, payload: dict):
        self._query = query
        self.payload = payload
        self.cmd = payload.get("cmd")
        self.replied = False

    def reply(self, **values) -> None:
        body = dict({"ok": True}, **values)
        self._query.reply(self._query.key_expr, json.dumps(body, default=_plain).encode())
        self._query.drop()
        self.replied = True

    def fail(self, error: str) -> None:
        self._query.reply(self._query.key_expr, json.dumps({"ok": False, "error": error}).encode())
        self._query.drop()
        self.replied = True


class Service:
    """Context manager around one service's Zenoh session."""

    def __init__(self, name: str, run_id: str, zenoh_options: ZenohOptions, *, log=None, sched_fifo: int = 0,
                 cpus: tuple = ()):
        self.name = name
        self.sched_fifo_requested = sched_fifo
        self.sched_fifo = False
        self.cpus = tuple(cpus)
        self.run_id = topics.check_run_id(run_id)
        self.zenoh_options = zenoh_options
        self.stop = threading.Event()
        self.links: dict[str, LinkCounters] = {}
        self._control: queue.Queue = queue.Queue()
        self._publishers = {}
        self._subscribers = []
        self._log = log or (lambda msg: print(f"[{name}] {msg}", file=sys.stderr, flush=True))
        self.session = None
        self.profile = ProcessProfile(name)
        self._log_seq = -1  # lines published on service/log

    def log(self, msg: str, level: int = 2) -> None:
        """Log a line to stderr and, once the session is open, on ``service/log`` (recorded
        with the episode it falls in; the visual topics show it as a foxglove.Log line)."""
        self._log(msg)
        if self.session is None:
            return
        from services.runtime.messages import SERVICE_LOG

        try:
            pub = self._publishers.get("service/log") or self.publisher("service/log", realtime=False)
            self._log_seq += 1
            pub.put(SERVICE_LOG.encode(seq=self._log_seq, stamp_ns=0, sent_ns=time.monotonic_ns(), role=self.name,
                                       level=int(level), text=str(msg)))
        except Exception:  # noqa: BLE001 - the line is on stderr; the bus is a copy
            pass

    def __enter__(self) -> "Service":
        if self.sched_fifo_requested:
            # before the session: the threads Zenoh starts inherit the policy (a loop
            # under FIFO whose Zenoh threads are not waits for its own messages behind
            # every ordinary process on the machine)
            from services.runtime.loop import set_timer_slack, try_sched_fifo

            priority = 50 if self.sched_fifo_requested is True else int(self.sched_fifo_requested)
            self.sched_fifo = priority if try_sched_fifo(priority) else False
            set_timer_slack(1)
        if self.cpus:
            import os

            # before the session, like the policy: Zenoh's threads inherit the affinity
            os.sched_setaffinity(0, self.cpus)
        self.profile.start()
        self.session = open_session(self.zenoh_options)
        self._queryable = self.session.declare_queryable(topics.control(self.run_id, self.name), self._on_query)
        self._token = self.session.liveliness().declare_token(topics.alive(self.run_id, self.name))
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, self._on_signal)
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers.clear()
        self._token.undeclare()
        self._queryable.undeclare()
        self.session.close()
        path = self.profile.stop()
        if path is not None:
            self.log(f"profile written to {path}")

    def _on_signal(self, signum, frame) -> None:
        self.log(f"signal {signal.Signals(signum).name}: stopping")
        self.stop.set()

    # --------------------------------------------------------------- control

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            payload = json.loads(query.payload.to_bytes()) if query.payload is not None else {}
            if not isinstance(payload, dict):
                raise ValueError("control request must be a JSON object")
        except (ValueError, UnicodeDecodeError) as exc:
            query.reply(query.key_expr, json.dumps({"ok": False, "error": f"bad request: {exc}"}).encode())
            query.drop()
            return
        self._control.put(ControlRequest(query, payload))

    def next_control(self, timeout: float | None = None) -> ControlRequest | None:
        try:
            return self._control.get(timeout=timeout) if timeout else self._control.get_nowait()
        except queue.Empty:
            return None

    def serve(self, handlers: dict, status=None, idle=None) -> None:
        """Answer control requests until 'shutdown' or a signal.

        ``handlers[cmd](payload)`` returns the reply's fields (or None); a
        handler's KeyError/ValueError/TypeError/OSError becomes a failed reply,
        never a dead service.  'status' replies ``status()`` plus the link
        statistics; ``idle()`` runs between requests (every 50 ms at most).
        """
        known = ", ".join(sorted(handlers) + ["status", "shutdown"])
        while not self.stop.is_set():
            req = self.next_control(timeout=0.05)
            if idle is not None:
                idle()
            if req is None:
                continue
            if req.cmd == "shutdown":
                req.reply()
                return
            if req.cmd == "status":
                req.reply(**(status() if status else {}), links={k: v.to_dict() for k, v in self.links.items()})
                continue
            handler = handlers.get(req.cmd)
            if handler is None:
                req.fail(f"unknown command {req.cmd!r} ({known})")
                continue
            try:
                if getattr(handler, "replies_itself", False):
                    # it replies, then goes on (the robot's 'run': the episode follows the reply)
                    handler(req.payload, req.reply)
                else:
                    req.reply(**(handler(req.payload) or {}))
            except (KeyError, ValueError, TypeError, OSError) as exc:
                if not req.replied:
                    req.fail(f"{type(exc).__name__}: {exc}")
                else:
                    self.log(f"'{req.cmd}' failed after its reply: {type(exc).__name__}: {exc}", level=4)

    # ------------------------------------------------------------ publishing

    def publisher(self, topic: str, *, realtime: bool = True, drop_when_congested: bool = False):
        """A publisher on etar/<run_id>/<topic>; 1 kHz control topics use express
        delivery and REAL_TIME priority (DESIGN.md).  ``drop_when_congested``: a
        subscriber that falls behind loses messages (its sequence numbers show it)
        instead of blocking this publisher: what a realtime loop needs, where a slow
        recorder must not stop the robot; lockstep needs every message and blocks."""
        key = topics.key(self.run_id, topic)
        if realtime:
            cc = zenoh.CongestionControl.DROP if drop_when_congested else zenoh.CongestionControl.BLOCK
            pub = self.session.declare_publisher(key, express=True, priority=zenoh.Priority.REAL_TIME,
                                                 congestion_control=cc)
        else:
            pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        self._publishers[topic] = pub
        return pub

    def unsubscribe(self, subscriber) -> None:
        """Undeclare one subscriber ``subscribe`` returned: its messages stop costing this
        process anything (a node with nothing to do, e.g. the teacher between demonstrations)."""
        if subscriber in self._subscribers:
            self._subscribers.remove(subscriber)
            subscriber.undeclare()

    def subscribe(self, topic: str, on_message, *, decode: bool = True, every_tenth: bool = False,
                  latest: bool = False, keep_tenth: bool = False):
        """Deliver (message dict, receive time ns, raw bytes) for every valid
        sample on etar/<run_id>/<topic>; garbage (including payloads over
        ``MAX_PAYLOAD_BYTES``) is counted in ``links``, never raised, and so are
        duplicates and messages older than the newest delivered (by ``seq``),
        which are dropped.

        ``every_tenth``: only the messages of every tenth robot cycle (stamp a
        multiple of 10 ms), told from the raw bytes before anything is decoded: a
        100 Hz consumer of a 1 kHz topic then pays for the other nine at the cost
        of a byte comparison.

        ``latest``: for a realtime consumer that needs only the current data (the
        sensor, the estimator, the commander's measurements).  When it gets to the
        next message it takes the newest one that has arrived and skips the older
        ones: one that fell behind (a stall, a crowded CPU) starts again from the
        present instead of working through a stale backlog.  Skipped messages are
        never decoded; they show as gaps in the sequence numbers (``lost``) and, as
        far as this process saw them, in ``skipped``.  Zenoh keeps the newest
        samples in a ring (``zenoh.handlers.RingChannel``: 1 sample, 10 with
        ``every_tenth`` so that a tenth cycle is among them) and drops older ones
        without waking Python; one thread of this process drains it.  Never for
        the recorder or for lockstep, which need every message.  ``keep_tenth``
        (with ``latest``): a tenth cycle's message in the backlog is delivered
        before the newest instead of skipped (the sensor: the estimator needs the
        wrench of every tenth cycle); the ring then holds 10.

        ``"**"`` (every topic of the run, undecoded: the recorder's): Zenoh queues
        the samples (``FifoChannel``) and one thread takes what has come every
        ``BATCH_S``, so a consumer that needs every message but not at once wakes a
        few hundred times a second instead of once per message.
        Returns the subscriber (for ``unsubscribe``)."""
        if topic == "**":
            return self._subscribe_all(on_message)
        message_type: MessageType | None = BY_TOPIC.get(topic)
        stride = ESTIMATOR_STRIDE if every_tenth else STRIDES.get(topic, 1)
        counters = self.links.setdefault(topic, LinkCounters(sequence=SequenceTracker(stride=stride)))

        def deliver(raw: bytes, recv: int) -> None:
            counters.received += 1
            msg = None
            if decode and message_type is not None:
                try:
                    msg = message_type.decode(raw)
                except MessageError as exc:
                    counters.bad += 1
                    counters.last_error = str(exc)
                    return
                counters.latency.add(recv - msg["sent_ns"])
                verdict = counters.sequence.add(msg["seq"])
                if verdict is STALE:
                    counters.stale_run += 1
                    if counters.stale_run >= RESYNC_AFTER:
                        # this many older ones in a row are the stream itself: the newest
                        # seen was forged far ahead, and would otherwise silence the link
                        counters.sequence.resync(msg["seq"])
                        counters.resyncs += 1
                        verdict = FRESH
                if verdict is not FRESH:
                    # a copy, or older than what was acted on: within a run every topic's
                    # seq only grows (one robot, its FRI cycles), so this is a replay or a
                    # duplicate from the network or a foreign peer; acting on it would
                    # answer a cycle twice or go back in time
                    counters.dropped += 1
                    return
                counters.stale_run = 0
            try:
                on_message(msg, recv, raw)
            except Exception as exc:  # a bad message must not kill the subscriber thread
                counters.bad += 1
                counters.last_error = f"{type(exc).__name__}: {exc}"

        key = topics.key(self.run_id, topic)
        if latest:
            sub = self.session.declare_subscriber(key, zenoh.handlers.RingChannel(
                ESTIMATOR_STRIDE if every_tenth or keep_tenth else 1))
            deliver = self.profile.wrap(deliver)
            ring = sub.handler  # not the subscriber: undeclaring it while a thread waits in its recv() fails

            def drain() -> None:
                try:
                    while True:
                        raw = ring.recv().payload.to_bytes()
                        recv = now_ns()
                        if every_tenth and not tenth_cycle(raw):
                            raw = None
                        while (sample := ring.try_recv()) is not None:
                            newer = sample.payload.to_bytes()
                            if every_tenth and not tenth_cycle(newer):
                                continue
                            if raw is not None:
                                if keep_tenth and tenth_cycle(raw):
                                    deliver(raw, recv)
                                else:
                                    counters.skipped += 1
                            raw, recv = newer, now_ns()
                        if raw is not None:
                            deliver(raw, recv)
                except zenoh.ZError:
                    return  # undeclared: the ring is closed

            # started from the thread that subscribes: under --sched-fifo it inherits the policy
            threading.Thread(target=drain, name=f"latest {topic}", daemon=True).start()
            self._subscribers.append(sub)
            return sub

        def callback(sample: zenoh.Sample) -> None:
            recv = now_ns()
            raw = sample.payload.to_bytes()
            if every_tenth and not tenth_cycle(raw):
                return
            deliver(raw, recv)

        # Zenoh's default hands each sample to a Python thread.  Running the callback on
        # the network thread itself (Callback(indirect=False)) was measured worse: a
        # callback that publishes (the sensor) then blocks reception, and the sensor fell
        # 150 ms behind instead of 0.75 ms (hold run, 2 CPUs); no gain for the FRI link
        sub = self.session.declare_subscriber(key, self.profile.wrap(callback))
        self._subscribers.append(sub)
        return sub

    def _subscribe_all(self, on_sample):
        """Every sample of the run, undecoded and in batches: ``on_sample(topic, receive
        time ns, raw bytes, None)``, the receive time that of the batch's turn."""
        prefix = topics.prefix(self.run_id) + "/"
        cut = len(prefix)
        sub = self.session.declare_subscriber(prefix + "**", zenoh.handlers.FifoChannel(BATCH_CAPACITY))
        fifo = sub.handler
        stop = self.stop

        @self.profile.wrap
        def take(sample) -> None:
            on_sample(str(sample.key_expr)[cut:], now_ns(), sample.payload.to_bytes(), None)

        def drain() -> None:
            try:
                while True:
                    take(fifo.recv())  # the first of a batch: blocks until something comes
                    while (sample := fifo.try_recv()) is not None:
                        take(sample)
                    stop.wait(BATCH_S)
            except zenoh.ZError:
                return  # undeclared: the channel is closed

        threading.Thread(target=drain, name="batched **", daemon=True).start()
        self._subscribers.append(sub)
        return sub


_STAMP = re.compile(rb'^\{"seq":-?\d+,"stamp_ns":(\d+)')


def tenth_cycle(raw: bytes) -> bool:
    """True for a message stamped at an estimator instant (the encoder writes seq and
    stamp_ns first); anything unrecognisable passes, to be decoded and judged."""
    m = _STAMP.match(raw)
    return m is None or estimator_instant(int(m.group(1)))


def request(session: zenoh.Session, run_id: str, service: str, cmd: str, *, timeout: float = 10.0,
            **args) -> dict:
    """Send a control request and return the service's reply; raise on failure."""
    payload = json.dumps(dict(args, cmd=cmd)).encode()
    # the first reply is the answer: the query itself ends only once every route Zenoh
    # sent it on has answered or timed out (a host cut off mid-run held it 10 s)
    for r in session.get(topics.control(run_id, service), payload=payload, timeout=timeout):
        if r.ok is not None:
            body = json.loads(r.ok.payload.to_bytes())
            if not body.get("ok"):
                raise RuntimeError(f"{service} refused '{cmd}': {body.get('error')}")
            return body
    raise TimeoutError(f"{service} did not answer '{cmd}' within {timeout} s")


def alive_services(session: zenoh.Session, run_id: str, timeout: float = 1.0) -> set[str]:
    names = set()
    for r in session.liveliness().get(topics.key(run_id, "alive/*"), timeout=timeout):
        if r.ok is not None:
            names.add(str(r.ok.key_expr).rsplit("/", 1)[-1])
    return names
