"""The KRC's FRI endpoint over real loopback UDP, against a minimal remote written here
with plain sockets and ``struct`` at WIRE.md's offsets (not with the codec under test).
Nothing sleeps: the tests wait on the socket (``poll``'s timeout, ``settimeout``)."""

import socket
import sys
import struct
import time

import numpy as np
import pytest

from robot_sim.krc.link import FriLink
from robot_sim.krc.packets import CommandPacket, ControlMode, FriQuality, FriState, MeasurementPacket
from robot_sim.wire.fri_udp import FriUdpEndpoint
from tests.support import wait_until

# FRI datagrams with answer deadlines: alone (make test runs these first, with nothing beside them)
pytestmark = [pytest.mark.serial, pytest.mark.alone]

WAIT_S = 2.0  # the longest any datagram may take on loopback before a test fails
POSE = np.array([1.0, 0.0, 0.0, 0.5, 0.0, 1.0, 0.0, 0.125, 0.0, 0.0, 1.0, 0.25])
Q = np.linspace(-0.5, 0.5, 7)


class Remote:
    """A bare FRI 1.0 remote: receives 916-byte measurements, answers with 376-byte
    commands to the address the measurement came from, echoing its sendSeqCount."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(WAIT_S)
        self.address = self.sock.getsockname()
        self.krc = None
        self.sent = 0

    def receive(self) -> bytes:
        data, self.krc = self.sock.recvfrom(4096)
        assert len(data) == 916 and struct.unpack_from("<H", data, 6)[0] == 0x2006
        return data

    def command(self, measurement: bytes, *, refl=None, stiffness=1000.0, tag=0.0, size=376, datagram_id=0x1005,
                flags=0x3500) -> bytes:
        """A Cartesian impedance answer holding the measured pose; ``tag`` in addTcpFT[0]."""
        out = bytearray(size)
        self.sent += 1
        refl = struct.unpack_from("<H", measurement, 0)[0] if refl is None else refl
        struct.pack_into("<4H", out, 0, self.sent & 0xFFFF, refl, size, datagram_id)
        struct.pack_into("<i", out, 8 + 64 + 15 * 4, 10)  # $FRI_FRM_INT[16] = 10 (Stanford's "start")
        if size >= 376:
            struct.pack_into("<I", out, 140, flags)
            out[144:172] = measurement[216:244]  # jntPos = msrJntPos
            out[172:220] = measurement[244:292]  # cartPos = msrCartPos
            struct.pack_into("<6f", out, 248, tag, 0, 0, 0, 0, 0)
            struct.pack_into("<6f", out, 328, stiffness, stiffness, stiffness, 100, 100, 100)
            struct.pack_into("<6f", out, 352, *[0.7] * 6)
        return bytes(out)

    def send(self, data: bytes) -> None:
        self.sock.sendto(data, self.krc)

    def answer(self, measurement: bytes, **kw) -> None:
        self.send(self.command(measurement, **kw))

    def close(self):
        self.sock.close()


@pytest.fixture
def remote():
    r = Remote()
    yield r
    r.close()


@pytest.fixture
def endpoint(remote):
    with FriUdpEndpoint(remote=remote.address) as ep:
        yield ep


def packet(seq: int, reflected: int = -1) -> MeasurementPacket:
    return MeasurementPacket(seq, reflected, seq * 1_000_000, FriState.MON, FriQuality.PERFECT, ControlMode.CART_IMP,
                             Q.copy(), POSE.copy(), np.zeros(6), 1.0, 1e-4, 1e-5, 0.0)


def wait_for(endpoint: FriUdpEndpoint, condition) -> None:
    """Poll until ``condition()`` holds (a datagram the remote sent has been read)."""
    def read_then_check():
        endpoint.poll(0.01)  # waits on the socket, up to 10 ms
        return condition()
    wait_until(lambda: condition() or read_then_check(), WAIT_S, "the endpoint read what the remote sent",
               poll_s=0.0, seen=lambda: endpoint.counters)


def test_each_measurement_is_answered_and_matched_across_the_counter_wrap(endpoint, remote):
    seqs = list(range(65_530, 65_545))  # the 16-bit counters wrap at 65 536
    for seq in seqs:
        assert endpoint.send(packet(seq, reflected=seq - 1))
        m = remote.receive()
        assert struct.unpack_from("<2H", m, 0) == (seq & 0xFFFF, (seq - 1) & 0xFFFF)
        assert remote.krc == endpoint.address  # the KRC sends from the socket it reads
        remote.answer(m, tag=float(seq % 1000))
        cmd = endpoint.poll(WAIT_S)
        assert cmd is not None, endpoint.last_reject_reason
        assert cmd.seq == seq and cmd.add_tcp_ft[0] == seq % 1000
        assert cmd.requested_mode == ControlMode.CART_IMP
        np.testing.assert_allclose(cmd.cart_pos, POSE, atol=1e-7)
        np.testing.assert_allclose(cmd.cart_stiffness, [1000.0] * 3 + [100.0] * 3)
        np.testing.assert_allclose(endpoint.command.jnt_pos, Q, atol=1e-7)
        assert endpoint.arrival_ns > 0
    c = endpoint.counters
    assert (c.sent, c.received, c.accepted) == (len(seqs), len(seqs), len(seqs))
    assert c.late == c.duplicate == c.unsent == c.wrong_size == c.wrong_id == c.invalid == 0
    assert endpoint.krl_from.ints[15] == 10  # $FRI_FRM_INT[16]


def test_a_duplicate_and_a_late_answer_are_dropped_and_counted(endpoint, remote):
    endpoint.send(packet(100))
    first = remote.receive()
    remote.answer(first, tag=1.0)
    remote.answer(first, tag=2.0)  # the same cycle again: a duplicate, the first one wins
    remote.send(remote.command(first, datagram_id=0x9999))  # a marker: once read, so is the duplicate
    wait_for(endpoint, lambda: endpoint.counters.wrong_id == 1)
    assert endpoint.counters.duplicate == 1
    assert endpoint.poll().add_tcp_ft[0] == 1.0

    endpoint.send(packet(101))  # the next cycle opens
    second = remote.receive()
    remote.answer(first, tag=3.0)  # late: it answers cycle 100
    remote.answer(second, tag=4.0)
    cmd = endpoint.poll(WAIT_S)
    assert cmd.seq == 101 and cmd.add_tcp_ft[0] == 4.0
    assert endpoint.counters.late == 1

    endpoint.send(packet(102))
    remote.receive()
    remote.answer(second, tag=5.0)  # an answer to the previous cycle only: nothing for this one
    wait_for(endpoint, lambda: endpoint.counters.late == 2)
    assert endpoint.poll() is None
    assert endpoint.counters.accepted == 2


def test_wrong_sizes_and_ids_are_counted_and_ignored(endpoint, remote):
    endpoint.send(packet(5))
    m = remote.receive()
    remote.send(b"")
    remote.send(b"\x01" * 10)
    remote.send(remote.command(m, size=375))
    remote.send(remote.command(m, size=377))
    remote.send(m)  # a measurement sent back: 916 bytes
    remote.send(b"\0" * 5000)  # longer than the endpoint's buffer: cut, still the wrong size
    remote.send(remote.command(m, datagram_id=0x2006))
    remote.answer(m, refl=6)  # answers a cycle not sent yet
    remote.answer(m, tag=7.0)
    cmd = endpoint.poll(WAIT_S)
    assert cmd is not None and cmd.add_tcp_ft[0] == 7.0
    c = endpoint.counters
    assert (c.wrong_size, c.wrong_id, c.unsent, c.accepted, c.received) == (6, 1, 1, 1, 9)


def test_an_invalid_command_is_dropped_and_a_valid_one_after_it_accepted(endpoint, remote):
    endpoint.send(packet(9))
    m = remote.receive()
    remote.answer(m, stiffness=1e6)  # beyond the LWR's 5000 N/m
    remote.answer(m, tag=8.0)
    cmd = endpoint.poll(WAIT_S)
    assert cmd is not None and cmd.add_tcp_ft[0] == 8.0
    assert endpoint.counters.invalid == 1 and endpoint.counters.duplicate == 0


def test_a_command_before_any_measurement_is_ignored(remote):
    with FriUdpEndpoint(remote=remote.address) as ep:
        remote.sock.sendto(remote.command(bytes(916)), ep.address)
        wait_for(ep, lambda: ep.counters.received == 1)
        assert ep.counters.unsent == 1 and ep.poll() is None and ep.open_seq is None


def test_a_stranger_cannot_answer_or_send_krl_requests(endpoint, remote):
    """A KRC answers the remote it was configured for: a well-formed answer to the open cycle
    from another port, carrying a KRL request ($FRI_FRM_INT[16] = 20, "stop"), is counted
    and ignored whole; the remote's own answer after it is the cycle's."""
    endpoint.send(packet(40))
    m = remote.receive()
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        stop = bytearray(remote.command(m, tag=9.0))
        struct.pack_into("<i", stop, 8 + 64 + 15 * 4, 20)
        for _ in range(5):
            stranger.sendto(bytes(stop), endpoint.address)
        wait_for(endpoint, lambda: endpoint.counters.foreign == 5)
    finally:
        stranger.close()
    assert endpoint.poll() is None and endpoint.krl_from is None and endpoint.counters.accepted == 0
    assert "not the remote" in endpoint.last_reject_reason
    remote.answer(m, tag=3.0)
    cmd = endpoint.poll(WAIT_S)
    assert cmd is not None and cmd.add_tcp_ft[0] == 3.0 and endpoint.krl_from.ints[15] == 10


def test_a_remote_named_localhost_is_the_loopback_address_it_sends_from(remote):
    with FriUdpEndpoint(remote=("localhost", remote.address[1])) as ep:
        ep.send(packet(1))
        remote.answer(remote.receive(), tag=2.0)
        assert ep.poll(WAIT_S).add_tcp_ft[0] == 2.0 and ep.counters.foreign == 0


def test_commands_without_cartesian_flags_take_the_defaults(endpoint, remote):
    endpoint.send(packet(3))
    m = remote.receive()
    remote.answer(m, flags=0x0001, stiffness=4000.0)  # joint position only, while the KRC is in CART_IMP
    cmd = endpoint.poll(WAIT_S)
    assert cmd.requested_mode == ControlMode.POSITION  # FriLink counts it as a mode mismatch
    np.testing.assert_array_equal(cmd.cart_stiffness, np.zeros(6))  # not flagged: hold_measured_pose's


def test_the_endpoint_carries_a_fri_link_into_command_mode(endpoint, remote):
    """The integration's path: FriLink's measurement out through the socket, the remote's
    answer back into FriLink.receive (synthetic times: the link judges the deadline)."""
    link = FriLink()
    link.start(0)
    link.request_command_mode()
    t, cycle = 0, link.config.cycle_ns
    endpoint.krl_to.ints[15] = 10  # what a KRL program would report in $FRI_TO_INT[16]
    for _ in range(link.config.perfect_hold_cycles + 5):
        m = link.measurement(t, Q, POSE, np.zeros(6))
        endpoint.send(m)
        data = remote.receive()
        assert struct.unpack_from("<i", data, 72 + 15 * 4)[0] == 10
        assert struct.unpack_from("<H", data, 144)[0] == int(link.state)
        remote.answer(data, tag=float(m.seq % 100))
        cmd = endpoint.poll(WAIT_S)
        assert link.receive(cmd, t + 100_000), link.last_reject_reason
        out = link.end_cycle(t + cycle)
        t += cycle
    assert out.state == FriState.CMD and not out.hold
    assert out.command.add_tcp_ft[0] == m.seq % 100
    stats = link.statistics()
    assert stats.missed == 0 and stats.corrupt == 0 and endpoint.counters.accepted == stats.answered


def test_an_unreachable_remote_does_not_raise():
    with FriUdpEndpoint(remote=("127.0.0.1", 9)) as ep:  # nothing listens on port 9 (discard)
        for seq in range(1, 4):
            ep.send(packet(seq))
            assert ep.poll() is None
        assert ep.counters.sent + ep.counters.send_errors == 3


def test_the_command_is_a_fresh_object_each_cycle(endpoint, remote):
    endpoint.send(packet(1))
    remote.answer(remote.receive(), tag=1.0)
    first = endpoint.poll(WAIT_S)
    endpoint.send(packet(2))
    assert endpoint.command is None
    remote.answer(remote.receive(), tag=2.0)
    second = endpoint.poll(WAIT_S)
    assert first is not second and first.add_tcp_ft[0] == 1.0 and second.add_tcp_ft[0] == 2.0
    assert isinstance(second, CommandPacket)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="kernel receive stamps (SO_TIMESTAMPNS) are Linux's")
def test_an_answer_read_late_is_stamped_when_it_arrived(endpoint, remote):
    """The KRC's loop may read the socket only at the end of its cycle: the latency FRI
    counts is to the datagram's arrival (the kernel's stamp), not to that read."""
    endpoint.send(packet(1))
    remote.answer(remote.receive())
    sent = time.monotonic_ns()
    time.sleep(0.05)  # the answer waits in the socket's buffer
    cmd = endpoint.poll()
    read = time.monotonic_ns()
    assert cmd is not None and cmd.seq == 1
    assert endpoint.arrival_ns < sent + 20_000_000 < read
