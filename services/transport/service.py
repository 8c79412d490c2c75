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
import os
import queue
import signal
import sys
import threading
import time

import zenoh

from services.runtime import topics
from services.runtime.messages import SERVICE_LOG, loads
from services.transport.profiling import ProcessProfile
from services.transport.session import ZenohOptions, open_session
from services.transport.subscriptions import LinkCounters, subscribe, subscribe_all

# set by the runner that spawns a service (services.transport.launch): its pid
RUNNER_PID_ENV = "ETAR_RUNNER_PID"
RUNNER_WATCH_S = 0.5


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
        try:
            pub = self._publishers.get(SERVICE_LOG.topic) or self.publisher(SERVICE_LOG.topic, realtime=False)
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
            # before the session, like the policy: Zenoh's threads inherit the affinity
            os.sched_setaffinity(0, self.cpus)
        self.profile.start()
        self.session = open_session(self.zenoh_options)
        self._queryable = self.session.declare_queryable(topics.control(self.run_id, self.name), self._on_query)
        self._token = self.session.liveliness().declare_token(topics.alive(self.run_id, self.name))
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, self._on_signal)
        runner = os.environ.get(RUNNER_PID_ENV)
        if runner and runner.isdigit():
            threading.Thread(target=self._watch_runner, args=(int(runner),), name="runner-watch", daemon=True).start()
        return self

    def _watch_runner(self, runner: int) -> None:
        """A runner that started this service and then vanished (killed with -9, which it
        cannot pass on) leaves it its orphan: the service stops as on a signal."""
        while not self.stop.wait(RUNNER_WATCH_S):
            if os.getppid() != runner:
                self.log(f"the runner that started this service (pid {runner}) is gone: stopping")
                self.stop.set()
                return

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
            payload = loads(query.payload.to_bytes()) if query.payload is not None else {}
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
                  latest: bool = False, keep_tenth: bool = False, horizon=None):
        """Deliver (message dict, receive time ns, raw bytes) for every valid sample on
        etar/<run_id>/<topic>, its link counted in ``links``; ``"**"``: every topic of the
        run, undecoded, in batches (``services.transport.subscriptions``).  Returns the
        subscriber (for ``unsubscribe``)."""
        if topic == "**":
            sub = subscribe_all(self.session, self.run_id, on_message, self.links, self.profile, self.stop)
        else:
            sub = subscribe(self.session, self.run_id, topic, on_message, self.links, self.profile, decode=decode,
                            every_tenth=every_tenth, latest=latest, keep_tenth=keep_tenth, horizon=horizon)
        self._subscribers.append(sub)
        return sub


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
