"""The robot node serving a lab's FRI 1.0 remote over UDP (loopback), cycle by cycle: what it
records of the wire on fri/datagram, and when.  No realtime clock: the test closes each
cycle once the remote's answer is on the socket, so nothing here depends on the machine."""

from __future__ import annotations

import base64
import time

import pytest

from robot_sim.wire.fri_datagrams import decode_command, decode_measurement
from services.transport.lab import edges
from services.nodes.robot import RobotConfig, RobotNode
from tests.robot_sim.fri_remote import Remote
from tests.support import wait_until


class Bus:
    def __init__(self):
        self.published = []  # (topic, message)

    def publish(self, topic: str, payload: bytes, message: dict | None = None) -> None:
        self.published.append((topic, message))

    def datagrams(self) -> list:
        out = [m for t, m in self.published if t == "fri/datagram"]
        self.published.clear()
        return out


class Clock:
    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)


def _answered(node: RobotNode) -> None:
    wait_until(node.udp.answered, 2.0, "the remote's answer to this cycle", poll_s=0.0005)


@pytest.fixture
def served():
    with Remote("frilibrary", strategy=20) as remote:
        bus = Bus()
        config = RobotConfig(wire="udp", fri_remote=f"127.0.0.1:{remote.port}")
        node = RobotNode(config, bus, Clock(), mode="realtime", **edges("robot", config, Clock()))
        try:
            node.reset({"start": [0.57, -0.05, 0.3], "kind": "served", "episode": 0})
            node.begin_episode()
            yield node, bus
        finally:
            node.close()


def test_a_cycles_datagrams_are_recorded_after_its_step_measurement_first(served):
    node, bus = served
    for _ in range(20):
        seq, _ = node.open_cycle()
        # measured and sent; its copy for the recording waits until the cycle has stepped
        assert bus.datagrams() == []
        _answered(node)
        node.close_cycle(None)
        measurement, command = bus.datagrams()
        assert (measurement["direction"], command["direction"]) == ("measurement", "command")
        assert measurement["seq"] == command["seq"] == seq
        rec = decode_measurement(base64.b64decode(measurement["bytes"]))
        assert int(rec["head"]["sendSeqCount"]) == seq & 0xFFFF == measurement["decoded"]["head"]["sendSeqCount"]
        cmd = decode_command(base64.b64decode(command["bytes"]))
        assert int(cmd["head"]["reflSeqCount"]) == seq & 0xFFFF
        assert command["sent_ns"] >= measurement["sent_ns"]


def test_a_step_that_fails_still_records_what_crossed_the_wire(served, monkeypatch):
    node, bus = served
    seq, _ = node.open_cycle()
    _answered(node)

    def fails(*a, **k):
        raise RuntimeError("the step failed")

    monkeypatch.setattr(node.cell, "end_cycle", fails)
    with pytest.raises(RuntimeError):
        node.close_cycle(None)
    assert [(d["direction"], d["seq"]) for d in bus.datagrams()] == [("measurement", seq), ("command", seq)]


def test_a_cycle_left_open_by_a_failed_episode_is_not_recorded_in_the_next(served):
    node, bus = served
    node.open_cycle()  # the episode fails here: the cycle is never closed
    node.begin_episode()
    node.cell.end_cycle()  # the KRC's own bookkeeping, as a restarted episode would find it
    seq, _ = node.open_cycle()
    _answered(node)
    node.close_cycle(None)
    assert [(d["direction"], d["seq"]) for d in bus.datagrams()] == [("measurement", seq), ("command", seq)]
