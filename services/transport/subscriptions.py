"""Subscriptions of a service process: messages decoded once and checked (garbage, duplicates,
replays counted per link, never raised), only what a node needs delivered (every tenth
cycle, the newest sample), and the whole run in batches for the recorder."""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass, field

import zenoh

from services.runtime import topics
from services.runtime.messages import (BY_TOPIC, ESTIMATOR_STRIDE, ROBOT_CONTACT, ROBOT_STATE, STRIDES, MessageError,
                                      MessageType, estimator_instant)
from services.runtime.timing import FRESH, STALE, Histogram, SequenceTracker, on_the_clock

# the wildcard subscription (the recorder's) takes what has arrived every BATCH_S, from
# a queue of ~10 s of every message of a run; when full, Zenoh holds further samples
# back (the publishers' congestion control decides what drops)
BATCH_S = 0.005
BATCH_CAPACITY = 50_000
# older messages in a row after which a link takes them as its stream again: a replayed
# copy comes between new ones, the real stream behind a forged far-ahead seq does not
# (50 cycles: FRI command mode drops, and comes back, rather than the link going silent)
RESYNC_AFTER = 50
# the robot's measurements: one every cycle of the run, so their seq never jumps.  A receiver
# of one takes a jump as the stream only once the next message continues it, and a newest
# that nothing continued as a forgery once the stream shows up far below it
# (``_measurement_judged``): one robot/state forged far ahead once ended a lockstep run
# ("service teacher stopped answering"; bench/replay_duplicates.py --forge-measurements)
CONTIGUOUS = (ROBOT_STATE.topic, ROBOT_CONTACT.topic)


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
    them as its stream again (the newest had been forged far ahead); ``off_clock``:
    messages whose publish stamp cannot be on this clock (``on_the_clock``), counted
    instead of their "latency"; ``ahead``: messages past the link's ``horizon`` (a seq
    no genuine one can have yet) or, on a ``CONTIGUOUS`` stream, far past its newest with
    nothing continuing them yet, dropped."""

    received: int = 0
    bad: int = 0
    skipped: int = 0
    dropped: int = 0
    resyncs: int = 0
    stale_run: int = 0
    ahead: int = 0
    off_clock: int = 0
    last_error: str = ""
    jump: int | None = None  # a contiguous stream's seq far past the newest, not yet continued
    continued: bool = False  # a contiguous stream's newest was followed by the next
    subscribed: bool = True  # (re)subscribed since the last message: a jump is the time it was not
    latency: Histogram = field(default_factory=Histogram)
    sequence: SequenceTracker = field(default_factory=SequenceTracker)

    def count_bad(self, error: str) -> None:
        """One message that did not decode, or whose handler raised: counted, its error kept."""
        self.bad += 1
        self.last_error = error

    def to_dict(self) -> dict:
        seq = self.sequence.to_dict()
        return {"received": self.received, "bad": self.bad, "skipped": self.skipped, "dropped": self.dropped,
                "resyncs": self.resyncs, "ahead": self.ahead, "off_clock": self.off_clock, "last_error": self.last_error,
                "latency": self.latency.summary(), "lost": seq["lost"], "out_of_order": seq["out_of_order"],
                "duplicates": seq["duplicates"]}


def _measurement_judged(counters: LinkCounters, seq: int) -> bool:
    """A ``CONTIGUOUS`` stream's message before its sequence is judged: False to drop it (a
    jump far past the newest, counted ``ahead`` until the next message continues from it);
    the newest is dropped for ``seq`` when nothing ever continued it and ``seq`` is far
    below it (a forged first message; the link resynchronises at once)."""
    tracker = counters.sequence
    newest, reach = tracker.highest, tracker.max_gap * tracker.stride
    if counters.subscribed:
        # the first since the link was (re)declared (the teacher's, episode by episode): a jump
        # is the cycles it did not listen to; a forger's first is left behind once the stream comes
        counters.subscribed, counters.continued, counters.jump = False, False, None
        return True
    if newest is None or abs(seq - newest) <= reach:
        counters.continued = counters.continued or (newest is not None and newest < seq)
        return True
    if seq > newest:
        held, counters.jump = counters.jump, seq
        if held is not None and 0 < seq - held <= reach:
            counters.jump, counters.continued = None, True  # the stream went on from there
            return True
        counters.ahead += 1
        return False
    if not counters.continued:
        tracker.resync(seq)  # so that seq is the newest: judged FRESH below
        counters.resyncs += 1
    return True


def _judged_delivery(counters: LinkCounters, message_type: MessageType | None, on_message, horizon=None,
                     contiguous: bool = False):
    """``deliver(raw, recv)``: decoded with ``message_type`` (None: not decoded), judged by its
    ``seq`` (duplicates, replays and stale ones dropped and counted; ``contiguous``: a stream
    whose seq never jumps, ``_measurement_judged``), then handed on; a bad message is counted
    in ``counters``, never raised."""

    def deliver(raw: bytes, recv: int) -> None:
        counters.received += 1
        msg = None
        if message_type is not None:
            try:
                msg = message_type.decode(raw)
            except MessageError as exc:
                counters.count_bad(str(exc))
                return
            except Exception as exc:  # noqa: BLE001 - a decoder's own bug (tests/services/recordings/test_fuzz.py
                # looks for them) must not end a latest subscriber's drain thread: counted, named
                counters.count_bad(f"{type(exc).__name__} while decoding: {exc}")
                return
            latency = recv - msg["sent_ns"]
            if on_the_clock(latency):
                counters.latency.add(latency)
            else:
                counters.off_clock += 1
            if horizon is not None and msg["seq"] > horizon():
                # past anything the publisher's counterpart has sent: acting on it, or letting
                # it set the newest, is what a forger wants
                counters.ahead += 1
                counters.dropped += 1
                return
            if contiguous and not _measurement_judged(counters, msg["seq"]):
                counters.dropped += 1
                return
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
            counters.count_bad(f"{type(exc).__name__}: {exc}")


    return deliver


def _subscribe_newest(session, key: str, topic: str, deliver, counters: LinkCounters, *, every_tenth: bool,
                      keep_tenth: bool):
    """``subscribe``'s ``latest``: a ring Zenoh keeps the newest samples in, drained by one
    thread that delivers the newest (and, with ``keep_tenth``, a tenth cycle's on the way)."""
    sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(
        ESTIMATOR_STRIDE if every_tenth or keep_tenth else 1))
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
    return sub


def subscribe(session, run_id: str, topic: str, on_message, links: dict, profile, *, decode: bool = True,
              every_tenth: bool = False, latest: bool = False, keep_tenth: bool = False, horizon=None):
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

    ``horizon``: ``horizon()`` is the newest seq a genuine message can carry now; one
    past it is counted (``ahead``) and dropped before the sequence is judged: a foreign
    peer's forged far ahead would otherwise make every real one after it look old.

    ``"**"`` (every topic of the run, undecoded: the recorder's): Zenoh queues
    the samples (``FifoChannel``) and one thread takes what has come every
    ``BATCH_S``, so a consumer that needs every message but not at once wakes a
    few hundred times a second instead of once per message.
    Returns the subscriber (for ``unsubscribe``)."""
    message_type: MessageType | None = BY_TOPIC.get(topic)
    stride = ESTIMATOR_STRIDE if every_tenth else STRIDES.get(topic, 1)
    counters = links.setdefault(topic, LinkCounters(sequence=SequenceTracker(stride=stride)))
    counters.subscribed = True

    deliver = _judged_delivery(counters, message_type if decode else None, on_message, horizon,
                               contiguous=topic in CONTIGUOUS)
    key = topics.key(run_id, topic)
    if latest:
        return _subscribe_newest(session, key, topic, profile.wrap(deliver), counters, every_tenth=every_tenth,
                                 keep_tenth=keep_tenth)

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
    sub = session.declare_subscriber(key, profile.wrap(callback))
    return sub


def subscribe_all(session, run_id: str, on_sample, links: dict, profile, stop: threading.Event):
    """Every sample of the run, undecoded and in batches: ``on_sample(topic, receive
    time ns, raw bytes, None)``, the receive time that of the batch's turn.  A sample
    ``on_sample`` raises on (a recording's full disk) is counted in ``links["**"]``, made
    at the first, and the next is taken: the thread goes on."""
    prefix = topics.prefix(run_id) + "/"
    cut = len(prefix)
    sub = session.declare_subscriber(prefix + "**", zenoh.handlers.FifoChannel(BATCH_CAPACITY))
    fifo = sub.handler

    @profile.wrap
    def take(sample) -> None:
        try:
            on_sample(str(sample.key_expr)[cut:], now_ns(), sample.payload.to_bytes(), None)
        except Exception as exc:  # noqa: BLE001 - counted and named; one bad sample must not end the drain
            counters = links.get("**") or links.setdefault("**", LinkCounters())
            counters.count_bad(f"{type(exc).__name__}: {exc}")

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
    return sub



_STAMP = re.compile(rb'^\{"seq":-?\d+,"stamp_ns":(\d+)')


def tenth_cycle(raw: bytes) -> bool:
    """True for a message stamped at an estimator instant (the encoder writes seq and
    stamp_ns first); anything unrecognisable passes, to be decoded and judged."""
    m = _STAMP.match(raw)
    return m is None or estimator_instant(int(m.group(1)))


