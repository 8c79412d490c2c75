"""Nodes and the bus they publish through.

A **node** is one role of the cell (robot, ft_sensor, teacher, phase_estimator,
impedance_commander, recorder) as an object: it declares what it subscribes to
and publishes (``Subscription``, ``Publication``), takes decoded messages with
their receive time, answers control requests (``handlers``) and publishes
encoded messages through a ``Bus``.  It never opens a session and never reads a
clock: the time comes from the ``Clock`` it is given.

A **transport** carries nodes: ``services.transport.process`` puts one node in its
own process on a Zenoh session (realtime or lockstep), ``services.transport.inproc``
puts every node of a run in one process on an in-memory bus (lockstep).  The
same node, the same messages, the same recordings (tested).

Handlers are called as ``handler(msg, recv_ns, raw)``: the decoded message
(``services.runtime.messages``; ``None`` for a subscription with
``decode=False``), the receive time on the node's clock, and the payload bytes
as they crossed the wire.  A wildcard subscription (``"**"``, the recorder's)
is called as ``handler(topic, recv_ns, raw, message)``, ``message`` the decoded
message when the bus has it without decoding (in memory), else None.  A handler that raises is
counted by the transport as a bad message; it never stops the node.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Protocol


class Clock(Protocol):
    def now_ns(self) -> int: ...

    def sleep(self, seconds: float) -> None: ...


class MonotonicClock:
    """CLOCK_MONOTONIC: what every process on one host shares (one-way latencies)."""

    now_ns = staticmethod(time.monotonic_ns)
    sleep = staticmethod(time.sleep)


class FakeClock:
    """A clock that moves only when told (tests; ``sleep`` advances it)."""

    def __init__(self, start_ns: int = 0):
        self.t = int(start_ns)

    def now_ns(self) -> int:
        return self.t

    def advance(self, ns: int) -> None:
        self.t += int(ns)

    def sleep(self, seconds: float) -> None:
        self.advance(round(seconds * 1e9))


class Bus(Protocol):
    carries_dicts: bool  # whether a published message's dict reaches anyone (in memory), or only its bytes

    def publish(self, topic: str, payload: bytes, message: dict | None = None) -> None:
        """``payload``: the bytes that cross the wire and are recorded; ``message``,
        when given, what they decode to (``MessageType.pack``), which a bus that
        delivers in memory may hand over instead of decoding the bytes again."""


@dataclass(frozen=True)
class Subscription:
    topic: str  # relative to the run prefix; "**": every topic of the run
    handler: Callable
    decode: bool = True
    # only messages of every tenth robot cycle (stamp a multiple of 10 ms), told from
    # the raw bytes before anything is decoded: what a 100 Hz consumer of a 1 kHz topic needs
    every_tenth: bool = False
    # realtime: take the newest message when the node gets to it, skip the backlog
    # (the transport decides how; lockstep and in-process always deliver every one)
    latest: bool = False
    # with latest: a tenth cycle's message in the backlog is delivered, not skipped
    keep_tenth: bool = False
    # the newest seq a genuine message can carry now (the robot's answers: its own latest
    # measurement), or None: one past it is a foreign peer's, counted and dropped before it
    # can make the real stream look old
    horizon: Callable[[], int] | None = None


@dataclass(frozen=True)
class Publication:
    topic: str
    # 1 kHz control topics: express delivery at REAL_TIME priority (DESIGN.md)
    express: bool = True
    # realtime: a subscriber that falls behind loses messages instead of blocking the
    # publisher (a slow recorder must not stop the robot); lockstep always blocks
    drop_when_congested: bool = False


class Node:
    """The base of every role: ``name``, what it subscribes to and publishes,
    its control handlers and its status.  Subclasses set ``self.subscriptions``
    and ``self.publications`` in their constructor."""

    name = "node"

    def __init__(self, bus: Bus, clock: Clock):
        self.bus = bus
        self.clock = clock
        self.subscriptions: list[Subscription] = []
        self.publications: list[Publication] = []

    def handlers(self) -> dict[str, Callable[[dict], dict | None]]:
        """Control commands: ``cmd -> handler(payload) -> reply fields``.  A handler's
        KeyError/ValueError/TypeError/OSError becomes a failed reply."""
        return {}

    def status(self) -> dict:
        return {}

    @property
    def listening(self) -> bool:
        """Whether the node has use for its subscriptions now.  A node with nothing to do
        (the teacher between demonstrations, the commander before its first
        reproduction) says False, and a realtime transport then stops its messages
        from arriving at all: on two CPUs, a 1 kHz stream decoded only to be ignored
        costs the FRI chain its deadlines.  Re-read after every control request;
        lockstep and in-process transports deliver regardless."""
        return True

    def idle(self, now_ns: int) -> None:
        """Called by a transport between events (at least every 50 ms while it serves)."""

    def quiescent(self) -> None:
        """The in-process transport has delivered everything and the cycle still waits:
        nothing more will arrive, so anything a node waits for will not come."""

    def close(self) -> None:
        """Finish what must be finished (files) when the transport stops."""
