"""A ``latest`` subscriber that falls behind takes the newest message, never a stale backlog;
the default subscriber (lockstep, the recorder) gets every message."""

import threading
import time

import pytest

from services.runtime import topics
from services.runtime.messages import ROBOT_CONTACT, ROBOT_STATE
from tests.services.conftest import service_with_peer

# service sessions over Zenoh on loopback
pytestmark = [pytest.mark.zenoh]


def contact(seq):
    return ROBOT_CONTACT.encode(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=time.monotonic_ns(),
                                wrench=[0.0] * 6, contact_force=[0.0] * 3, touching=[], true_phase=0, episode=0)


def state(seq):
    return ROBOT_STATE.encode(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=time.monotonic_ns(), reflected_seq=-1,
                              fri_state=1, fri_quality=3, control_mode=2, msr_jnt_pos=[0.0] * 7,
                              msr_cart_pos=[0.0] * 12, est_ext_tcp_ft=[0.0] * 6, answer_rate=1.0, latency_s=0.0,
                              jitter_s=0.0, miss_rate=0.0, safety=0, gravity_compensation=False, episode=0)


@pytest.fixture
def link():
    """A service (the subscriber) and a second session that publishes to it."""
    with service_with_peer("subscriber", "latest") as parts:
        yield parts


def wait_until_matched(publisher, timeout: float = 10.0) -> bool:
    matched = threading.Event()
    listener = publisher.declare_matching_listener(lambda status: status.matching and matched.set())
    try:
        return publisher.matching_status.matching or matched.wait(timeout)
    finally:
        listener.undeclare()


def counting(svc, run_id, topic):
    """A second, ordinary subscriber in the same session: it sees every message that
    reached the service, so the test knows when they have all arrived."""
    got = []
    sub = svc.session.declare_subscriber(topics.key(run_id, topic), lambda sample: got.append(1))
    return got, sub


def wait_for(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.01)
    return cond()


@pytest.mark.parametrize("latest", [True, False])
def test_a_subscriber_that_falls_behind(link, latest):
    svc, run_id, session = link
    seen, busy = [], threading.Event()

    def on_contact(msg, recv_ns, raw):
        seen.append(msg["seq"])
        if msg["seq"] == 1:
            busy.wait(10)  # stuck on the first while 2..50 arrive

    svc.subscribe("robot/contact", on_contact, latest=latest)
    arrived, counter = counting(svc, run_id, "robot/contact")
    pub = session.declare_publisher(topics.key(run_id, "robot/contact"))
    assert wait_until_matched(pub)
    pub.put(contact(1))
    assert wait_for(lambda: seen == [1])
    for seq in range(2, 51):
        pub.put(contact(seq))
    assert wait_for(lambda: len(arrived) == 50)  # all of them have arrived while the handler is stuck
    busy.set()
    assert wait_for(lambda: seen[-1] == 50)
    counter.undeclare()
    counters = svc.links["robot/contact"].to_dict()
    if latest:
        # the newest, not the backlog (the ring may take the one before it too, had the
        # newest not quite reached it when the handler let go)
        assert seen[0] == 1 and seen[-1] == 50 and len(seen) <= 3, seen
        assert counters["lost"] >= 47 and counters["received"] <= 3
    else:
        assert seen == list(range(1, 51))  # every one, in order
        assert counters["lost"] == 0 and counters["skipped"] == 0


def test_latest_every_tenth_takes_the_newest_tenth_cycle(link):
    svc, run_id, session = link
    seen, busy = [], threading.Event()

    def on_state(msg, recv_ns, raw):
        seen.append(msg["seq"])
        if msg["seq"] == 10:
            busy.wait(10)

    svc.subscribe("robot/state", on_state, every_tenth=True, latest=True)
    arrived, counter = counting(svc, run_id, "robot/state")
    pub = session.declare_publisher(topics.key(run_id, "robot/state"))
    assert wait_until_matched(pub)
    for seq in range(1, 11):
        pub.put(state(seq))
    assert wait_for(lambda: seen == [10])
    for seq in range(11, 58):  # tenth cycles 20..50 arrive, then 51..57 fill the ring with nine others
        pub.put(state(seq))
    assert wait_for(lambda: len(arrived) == 57)
    counter.undeclare()
    busy.set()
    for seq in range(58, 61):
        pub.put(state(seq))
    assert wait_for(lambda: seen[-1] == 60)
    assert seen[0] == 10 and seen[-1] == 60 and len(seen) <= 3  # 50 at most in between, never 20-40
    assert all(s % 10 == 0 for s in seen)


@pytest.mark.parametrize("latest", [True, False])
def test_a_foreign_message_that_does_not_decode_leaves_the_subscription_working(link, latest):
    """A float field holding 1 and 400 zeros (valid JSON) is counted bad, and the messages
    after it are delivered: it raised OverflowError out of the decoder, which ended the
    latest subscriber's drain thread, so the subscription went silent for good."""
    import json

    svc, run_id, session = link
    seen = []
    svc.subscribe("robot/contact", lambda msg, recv_ns, raw: seen.append(msg["seq"]), latest=latest)
    pub = session.declare_publisher(topics.key(run_id, "robot/contact"))
    assert wait_until_matched(pub)
    pub.put(contact(1))
    assert wait_for(lambda: seen == [1])
    bad = json.loads(contact(2))
    bad["contact_force"][0] = 10**400
    pub.put(json.dumps(bad).encode())
    assert wait_for(lambda: svc.links["robot/contact"].bad == 1)
    for seq in range(3, 6):
        pub.put(contact(seq))
        assert wait_for(lambda: seen[-1] == seq)
    assert seen == [1, 3, 4, 5]
    assert "401 digits, past 64 bits" in svc.links["robot/contact"].last_error


def test_a_decoder_that_fails_unexpectedly_does_not_end_the_subscription(link, monkeypatch):
    """Whatever a decoder raises besides MessageError (a bug of ours) is counted as a bad
    message and named; the latest subscriber's drain thread goes on."""
    from services.runtime.messages import MessageType

    svc, run_id, session = link
    seen = []
    real = MessageType.decode

    def flaky(self, raw):
        if b'"seq":2,' in raw:
            raise ZeroDivisionError("a decoder bug")
        return real(self, raw)

    monkeypatch.setattr(MessageType, "decode", flaky)
    svc.subscribe("robot/contact", lambda msg, recv_ns, raw: seen.append(msg["seq"]), latest=True)
    pub = session.declare_publisher(topics.key(run_id, "robot/contact"))
    assert wait_until_matched(pub)
    for seq in range(1, 5):
        pub.put(contact(seq))
        if seq == 2:
            assert wait_for(lambda: svc.links["robot/contact"].bad == 1)
        else:
            assert wait_for(lambda: seen[-1:] == [seq])
    assert seen == [1, 3, 4]
    assert svc.links["robot/contact"].last_error == "ZeroDivisionError while decoding: a decoder bug"


def test_a_sample_the_recorders_subscription_raises_on_is_counted_and_the_next_are_taken(link):
    """The recorder's ``**`` subscription: its handler raised on a full disk (the file could
    take no more), which ended the drain thread; every later sample went unseen and ending
    the episode waited out the recorder's wait for them.  Now counted, named, and the next
    one taken."""
    import json

    svc, run_id, session = link
    seen = []

    def on_sample(topic, recv_ns, raw, message):
        if b'"seq":2,' in raw:
            raise OSError(28, "No space left on device")
        seen.append((topic, json.loads(raw)["seq"]))

    svc.subscribe("**", on_sample)
    pub = session.declare_publisher(topics.key(run_id, "robot/contact"))
    assert wait_until_matched(pub)
    for seq in range(1, 5):
        pub.put(contact(seq))
    assert wait_for(lambda: len(seen) == 3)
    assert seen == [("robot/contact", 1), ("robot/contact", 3), ("robot/contact", 4)]
    assert svc.links["**"].bad == 1
    assert svc.links["**"].last_error == "OSError: [Errno 28] No space left on device"
