"""A real service process over Zenoh: it answers valid messages and survives garbage."""

import threading
import time

import numpy as np
import pytest
import zenoh

from services.transport import launch
from services.runtime import topics
from services.runtime.messages import FT_WRENCH, MAX_PAYLOAD_BYTES, ROBOT_CONTACT
from services.transport.service import request
from services.transport.session import ZenohOptions, open_session
from tests.support import wait_until

# service sessions over Zenoh on loopback
pytestmark = [pytest.mark.zenoh]


def wait_until_matched(publisher, timeout: float = 10.0) -> bool:
    """Until a subscriber somewhere matches ``publisher`` (Zenoh's matching status: an
    event, not a guess at how long a subscription takes to propagate)."""
    matched = threading.Event()
    listener = publisher.declare_matching_listener(lambda status: status.matching and matched.set())
    try:
        if publisher.matching_status.matching:
            return True
        return matched.wait(timeout)
    finally:
        listener.undeclare()


@pytest.fixture
def ft_sensor(tmp_path):
    endpoint = f"tcp/127.0.0.1:{launch.free_port()}"
    session = open_session(ZenohOptions(listen=(endpoint,)))
    run_id = f"proc-{int(time.time() * 1000)}"
    proc = launch.spawn("ft_sensor", ["--run-id", run_id, "--connect", endpoint, "--seed", "3"], tmp_path)
    try:
        launch.wait_alive(session, run_id, ["ft_sensor"], [proc], timeout=60)
        yield session, run_id, proc
    finally:
        codes = launch.stop([proc], grace=0.0)  # SIGINT at once: nobody asked it to shut down
        session.close()
        assert codes["ft_sensor"] == 0, proc.tail()  # SIGINT: a clean exit


def test_garbage_is_dropped_and_counted_valid_messages_are_answered(ft_sensor):
    session, run_id, proc = ft_sensor
    got, done = [], threading.Event()

    def on_wrench(sample):
        got.append(FT_WRENCH.decode(sample.payload.to_bytes()))
        if len(got) == 5:
            done.set()

    sub = session.declare_subscriber(topics.key(run_id, "ft/wrench"), on_wrench)
    # blocking when congested: what is tested is how the sensor counts what reaches it; with
    # Zenoh's default (drop) the 64 kB message below, in fragments, was lost in transit once
    # in CI (13 of 14 received), with the compose test's traffic beside it
    pub = session.declare_publisher(topics.key(run_id, "robot/contact"), congestion_control=zenoh.CongestionControl.BLOCK)
    assert wait_until_matched(pub), "the sensor's subscription never reached this publisher"
    for junk in (b"\x00\xff not json", b'{"seq": "one"}', b'{"seq":1,"stamp_ns":0,"sent_ns":0,"wrench":[NaN,0,0,0,0,0],'
                 b'"contact_force":[0,0,0],"touching":[],"true_phase":0,"episode":0}'):
        pub.put(junk)
    for k in range(5):
        pub.put(ROBOT_CONTACT.encode(seq=k + 1, stamp_ns=(k + 1) * 1_000_000, sent_ns=time.monotonic_ns(),
                                     wrench=np.array([0.0, 0.0, 2.45, 0.0, 0.0, 0.0]), contact_force=np.zeros(3),
                                     touching=[], true_phase=0, episode=0))
    assert done.wait(10), f"only {len(got)} answers"
    assert [m["seq"] for m in got] == [1, 2, 3, 4, 5]
    assert all(m["status"] == 0 for m in got)
    # untared: the tool's weight plus the sensor's bias
    from robot_sim.ati.sensor import AtiConfig

    assert abs(np.mean([m["wrench"][2] for m in got]) - (2.45 + AtiConfig.mini45().bias[2])) < 0.5
    status = request(session, run_id, "ft_sensor", "status")
    assert status["links"]["robot/contact"]["bad"] == 3
    assert status["links"]["robot/contact"]["received"] == 8
    with pytest.raises(RuntimeError, match="unknown command"):
        request(session, run_id, "ft_sensor", "explode")
    assert proc.alive()

    # from this foreign peer: exact copies, a stale message (an older cycle) and an
    # oversized one are counted and dropped; the next new cycle is answered once
    def contact(seq, **extra):
        return ROBOT_CONTACT.pack(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=time.monotonic_ns(),
                                  wrench=np.zeros(6), contact_force=np.zeros(3), touching=[], true_phase=0,
                                  episode=0)[0]

    n = len(got)
    oversized = contact(11)[:-1] + b',"pad":"' + b"x" * MAX_PAYLOAD_BYTES + b'"}'
    for raw in (contact(5), contact(5), contact(8), contact(7), contact(10), oversized):
        pub.put(raw)
    # the sensor answers in order: once cycle 10's answer is here, any answer to the
    # copies or the stale one would have come before it
    wait_until(lambda: any(m["seq"] == 10 for m in got[n:]), 10, "the answer to cycle 10",
               seen=lambda: [m["seq"] for m in got])
    assert [m["seq"] for m in got[n:]] == [8, 10], [m["seq"] for m in got]
    def contact_links():
        return request(session, run_id, "ft_sensor", "status")["links"]["robot/contact"]
    # the oversized one may come last (it is the longest on the wire)
    wait_until(lambda: contact_links()["received"] == 14, 10, "the sensor received the 14 messages", poll_s=0.05,
               seen=contact_links)
    links = contact_links()
    assert links["dropped"] == 3 and links["duplicates"] == 2 and links["out_of_order"] == 1, links
    assert links["bad"] == 4 and "byte limit" in links["last_error"], links
    # a well-formed message forged far ahead is dropped (the robot's measurements come every
    # cycle, and nothing continues it), and the real stream goes on (before, it was taken as the
    # newest, and the stream dropped as older until RESYNC_AFTER of it in a row)
    n = len(got)
    for seq in (10**12, *range(12, 81)):
        pub.put(contact(seq))
    wait_until(lambda: any(m["seq"] == 80 for m in got[n:]), 10, "the answer to cycle 80",
               seen=lambda: [m["seq"] for m in got[n:]][-5:])
    assert [m["seq"] for m in got[n:]] == list(range(12, 81))
    links = request(session, run_id, "ft_sensor", "status")["links"]["robot/contact"]
    assert links["ahead"] == 1 and links["resyncs"] == 0 and links["dropped"] == 3 + 1, links
    sub.undeclare()


def test_a_service_that_exits_when_asked_is_not_lost_and_its_exit_code_is_kept(tmp_path):
    """The runner's verdict on how the services ended (``runner._unclean_exits``) leaves out
    the lost ones; a service's token going away once it is asked to shut down is not a loss,
    or a service failing on its way out (an exit code, a signal) would pass unseen."""
    endpoint = f"tcp/127.0.0.1:{launch.free_port()}"
    session = open_session(ZenohOptions(listen=(endpoint,)))
    run_id = f"stop-{int(time.time() * 1000)}"
    supervisor = launch.Supervisor(session, run_id, tmp_path)
    try:
        supervisor.start({"recorder": ["--run-id", run_id, "--connect", endpoint, "--out-dir", str(tmp_path)]}, 60)
        codes = supervisor.stop(lambda: request(session, run_id, "recorder", "shutdown", timeout=5.0))
        time.sleep(0.5)  # a token's deletion still in flight would count now
        assert codes == {"recorder": 0} and supervisor.lost == {}, (codes, supervisor.lost)
    finally:
        supervisor.close()
        session.close()


def test_free_ports_are_below_the_ephemeral_range_distinct_and_bindable():
    """A port handed out is one no outgoing connection can be given before its user binds
    it (the kernel picks those from the ephemeral range), of the kind asked for."""
    import socket

    low = launch._ephemeral_range()[0]
    ports = {kind: [launch.free_port(kind) for _ in range(40)] for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM)}
    for kind, picked in ports.items():
        assert len(set(picked)) == len(picked)
        assert all(1024 <= p < low for p in picked), picked
        with socket.socket(socket.AF_INET, kind) as s:
            s.bind(("127.0.0.1", picked[-1]))


def test_the_runner_picks_another_port_when_its_first_is_taken(tmp_path, monkeypatch):
    """The runner's router port taken between its pick and its bind (CI: another run's
    peers took it) costs a second pick, not the run."""
    import socket

    from services.transport import zenoh_cell
    from services.transport.cell import Start

    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    picks = iter([taken.getsockname()[1], launch.free_port()])
    monkeypatch.setattr(zenoh_cell, "free_port", lambda: next(picks))
    try:
        cell = zenoh_cell.ZenohCell(f"port-{time.time_ns()}", Start("lockstep", tmp_path, lambda role: (None, ())), {})
        try:
            assert cell.endpoint != f"tcp/127.0.0.1:{taken.getsockname()[1]}"
            assert next(picks, None) is None  # it took the second pick
        finally:
            cell.stop([], before_report=False)
    finally:
        taken.close()


def test_a_teacher_subscribes_only_while_it_listens_and_the_robot_sees_its_token_first(tmp_path):
    """Lockstep over Zenoh: the teacher declares its subscriptions when reset for a
    demonstration, then its listening token; once the robot's session has the token, the
    robot's first message of the episode reaches the teacher, every time.  Idle, it
    receives nothing (its messages cost a lockstep run ~10 % of its CPU before)."""
    from services.nodes.teacher import TeacherConfig, TeacherNode
    from services.runtime.bus import MonotonicClock
    from services.transport.process import Listeners, NodeInputs, ZenohBus
    from services.transport.service import Service

    endpoint = f"tcp/127.0.0.1:{launch.free_port()}"
    run_id = f"listen-{time.time_ns()}"
    runner = open_session(ZenohOptions(listen=(endpoint,)))
    try:
        with Service("robot", run_id, ZenohOptions(connect=(endpoint,))) as robot, \
                Service("teacher", run_id, ZenohOptions(connect=(endpoint,))) as teacher_svc:
            bus = ZenohBus(teacher_svc, realtime=False)
            teacher = TeacherNode(TeacherConfig(), bus, MonotonicClock())
            bus.declare(teacher.publications)
            inputs = NodeInputs(teacher, teacher_svc, realtime=False)
            inputs.sync()
            assert inputs.declared == []  # idle from the start
            listeners = Listeners(robot)
            state = robot.publisher("robot/state", realtime=False)
            payload = b'{"seq":1}'  # garbage to the teacher, but counted as received: what is measured

            def received():
                c = teacher_svc.links.get("robot/state")
                return 0 if c is None else c.received

            keys = []
            for episode in [e // 2 for e in range(40)]:  # each episode twice: a reset after an idle
                key = inputs.after(teacher.reset)({"start": [0.5, 0.1, 0.3], "episode": episode})["listening"]
                assert key not in keys  # never one from before: its end may still be in transit
                keys.append(key)
                assert listeners.wait([key], 10.0) == []
                before = received()
                state.put(payload)
                wait_until(lambda: received() != before, 5.0, f"episode {episode}: the first message",
                           poll_s=0.001)
                assert received() == before + 1, f"episode {episode}: the first message was lost"
                inputs.after(teacher.idle_until_reset)({})
                assert inputs.declared == []
            # idle: nothing reaches it (its subscriptions are gone here, not only filtered)
            before = received()
            state.put(payload)
            time.sleep(0.3)
            assert received() == before
            assert listeners.wait([keys[-1]], 0.5) == [keys[-1]]
    finally:
        runner.close()


def test_the_robot_starts_an_episode_only_once_the_tokens_it_was_given_are_live(monkeypatch):
    """The robot's 'run' in lockstep over Zenoh waits for the listening tokens the runner
    passes on; without them it refuses, naming the token, and never starts."""
    from services.nodes.robot import RobotConfig, RobotNode
    from services.runtime.bus import MonotonicClock
    from services.transport import process
    from services.transport.collector import PausedCollector
    from services.transport.service import Service

    monkeypatch.setattr(process, "LISTENING_TIMEOUT_S", 0.5)
    endpoint = f"tcp/127.0.0.1:{launch.free_port()}"
    run_id = f"tokens-{time.time_ns()}"
    runner = open_session(ZenohOptions(listen=(endpoint,)))
    try:
        with Service("robot", run_id, ZenohOptions(connect=(endpoint,))) as svc:
            bus = process.ZenohBus(svc, realtime=False)
            node = RobotNode(RobotConfig(), bus, MonotonicClock())
            bus.declare(node.publications)
            node.reset({"start": [0.6, 0.0, 0.3], "episode": 0, "kind": "reproduction"})
            run = process._robot_handlers(node, svc, RobotConfig(), "lockstep", MonotonicClock(),
                                          PausedCollector())["run"]
            key = topics.listening(run_id, "teacher", "0.1")
            replies = []
            with pytest.raises(ValueError, match=f"no token {key}"):
                run({"max_seconds": 0.005, "listening": [key]}, lambda **r: replies.append(r))
            assert replies == []
            with pytest.raises(ValueError, match="listening must be a list"):
                run({"max_seconds": 0.005, "listening": key}, lambda **r: replies.append(r))
            token = runner.liveliness().declare_token(key)
            run({"max_seconds": 0.005, "listening": [key]}, lambda **r: replies.append(r))
            assert len(replies) == 1 and replies[0]["started"]
            token.undeclare()
    finally:
        runner.close()
