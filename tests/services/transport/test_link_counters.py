"""What a subscriber counts of each message it receives (services.transport.subscriptions)."""

import numpy as np

from services.runtime.messages import ROBOT_CONTACT
from services.transport.subscriptions import LinkCounters, _judged_delivery


def contact(seq: int, sent_ns: int) -> bytes:
    return ROBOT_CONTACT.encode(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=sent_ns, wrench=np.zeros(6),
                                contact_force=np.zeros(3), touching=[], true_phase=0, episode=0)


def test_a_stamp_off_the_receivers_clock_is_counted_apart_and_the_message_still_handed_on():
    """A foreign peer's stamp (sent_ns 1 on a host up 78 679 s, or one from the future) is no
    latency: counted as off the clock, the run's own latencies as they were; the message
    itself is judged by its seq as any other."""
    counters, got = LinkCounters(), []
    deliver = _judged_delivery(counters, ROBOT_CONTACT, lambda msg, recv, raw: got.append(msg["seq"]))
    now = 78_679 * 10**9
    deliver(contact(1, now - 300_000), now)
    deliver(contact(2, 1), now + 1_000_000)
    deliver(contact(3, now + 5 * 10**9), now + 2_000_000)
    deliver(contact(4, now + 2_900_000), now + 3_000_000)
    assert got == [1, 2, 3, 4]
    links = counters.to_dict()
    assert links["off_clock"] == 2
    assert links["latency"]["count"] == 2 and links["latency"]["max_us"] == 300.0
    assert links["latency"]["min_us"] == 100.0


def test_an_answer_past_the_robots_latest_measurement_is_dropped_and_the_real_ones_go_on():
    """A foreign peer's forged answers 997 cycles past each other, from before the run's own
    answers began, never make the real ones look old: past the horizon (the robot's latest
    measurement) they are counted as ahead and dropped; without the horizon the link would
    drop every real answer as older (it once ended a lockstep reproduction as unanswered)."""
    measured = [0]
    got, counters = [], LinkCounters()
    deliver = _judged_delivery(counters, ROBOT_CONTACT, lambda msg, recv, raw: got.append(msg["seq"]),
                               horizon=lambda: measured[0])
    blind = LinkCounters()
    blind_deliver = _judged_delivery(blind, ROBOT_CONTACT, lambda msg, recv, raw: None)
    forged = iter(range(10968, 10**6, 997))
    for seq in range(5693, 5713):
        for d in (deliver, blind_deliver):
            d(contact(next(forged), 1), 0)  # the forger's, then the run's own answer to cycle seq
        measured[0] = seq
        for d in (deliver, blind_deliver):
            d(contact(seq, 10), 20)
    assert got == list(range(5693, 5713))
    assert counters.to_dict()["ahead"] == 20 and counters.sequence.out_of_order == 0
    assert blind.sequence.out_of_order == 20  # what the robot's link did before it had a horizon


def _measurements_link():
    got, counters = [], LinkCounters()
    deliver = _judged_delivery(counters, ROBOT_CONTACT, lambda msg, recv, raw: got.append(msg["seq"]),
                               contiguous=True)
    return (lambda seq: deliver(contact(seq, 10), 20)), got, counters


def test_a_measurement_forged_far_ahead_mid_stream_is_dropped_and_the_stream_goes_on():
    """The robot's measurements come every cycle: a seq far past the newest, twice, each 997
    past the last (as bench/replay_duplicates.py's forger sends), between the real ones: the
    forgeries are counted ahead and dropped, the real ones all delivered.  Without the rule
    every real one after the first was dropped as older.  (A forger whose messages continue
    each other is taken for the stream: the receivers cannot know the robot's publisher.)"""
    send, got, counters = _measurements_link()
    forged = iter(range(1107, 10**6, 997))
    for seq in range(100, 110):
        send(seq)
    for seq in range(110, 130):
        if seq % 5 == 0:
            f = next(forged)
            send(f)
            send(f)
        send(seq)
    assert got == list(range(100, 130))
    assert counters.ahead == 8 and counters.dropped == 8 and counters.sequence.out_of_order == 0


def test_a_forged_first_measurement_is_left_behind_when_the_stream_shows_up_far_below_it():
    """A forger that publishes before the run's first measurement: its one message is taken
    (nothing came before it to judge it by), then the real stream, far below and never
    continuing it, takes over at once, not after 50 timed-out lockstep cycles."""
    send, got, counters = _measurements_link()
    send(5000)
    for seq in range(10, 30):
        send(seq)
        if seq == 15:
            send(5997)  # and more of the forger's, far ahead
    assert got == [5000, *range(10, 30)]
    assert counters.resyncs == 1 and counters.ahead == 1


def test_a_real_jump_of_the_stream_is_taken_once_the_next_message_continues_it():
    """A jump far past the newest that the next message continues (a realtime receiver past a
    long stall) is the stream: its first message is dropped, the rest delivered; a copy of the
    jump does not count as its continuation."""
    send, got, counters = _measurements_link()
    for seq in (1, 2, 3, 500, 500, 501, 502, 4):
        send(seq)
    assert got == [1, 2, 3, 501, 502]
    assert counters.ahead == 2 and counters.dropped == 3  # the jump and its copy; 4 is older than 502
