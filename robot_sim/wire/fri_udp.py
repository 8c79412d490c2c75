"""The KRC's FRI 1.0 endpoint on a real UDP socket.

A thin layer between the KRC's books (``robot_sim.krc.link.FriLink``) and a remote that
speaks FRI 1.0 (a lab program, the Stanford FRI Library, ``lwr_hw``): each cycle the
KRC :meth:`FriUdpEndpoint.send`\\ s its measurement datagram (``robot_sim.wire.fri_datagrams``)
to the remote's address, and :meth:`FriUdpEndpoint.poll` reads the command datagrams
that have arrived on the same socket and returns the cycle's answer.  As WIRE.md
says, the KRC initiates: the remote answers to the source address of the last
measurement it received, so one socket sends and receives.

Matching a command to a cycle follows ``FriLink.receive``: a command's
``reflSeqCount`` is unwrapped near the open cycle (``fri_wire.unwrap``); the first
well-formed, valid answer to the open cycle is *accepted*, a further one is a
*duplicate*, one answering an older cycle is *late*, one answering a cycle not sent
yet is *unsent*; a datagram from any address but the remote's is *foreign* and ignored
whole (its KRL requests too: a KRC answers the remote it was configured for, so a stray
sender on the network cannot start or stop command mode); a datagram of the wrong size or ``datagramId`` is counted
(``wrong_size``, ``wrong_id``) and ignored, and so is one that decodes to an invalid
``CommandPacket`` (``invalid``, the reason in ``last_reject_reason``).  Nothing
raises for what a remote sends.

What is not here: the deadline and the statistics (``FriLink`` keeps them; hand it
the accepted command with ``FriLink.receive``), the clock of a realtime loop, and the
KRL program behind ``$FRI_TO_*`` / ``$FRI_FRM_*`` (:attr:`FriUdpEndpoint.krl_to` is
sent with every measurement; :attr:`FriUdpEndpoint.krl_from` is the block of the
newest well-formed command, late ones included).  The endpoint reads no clock except
to stamp arrivals (``clock``, ``time.monotonic_ns`` by default, injectable; on Linux the
kernel's receive stamp says how long a datagram waited to be read, which is taken off).
"""

from __future__ import annotations

import select
import socket
import struct
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Self

import numpy as np

from robot_sim.krc.packets import CommandPacket, ControlMode, MeasurementExtras, MeasurementPacket
from robot_sim.krc.krl import KrlChannels
from robot_sim.wire.fri_datagrams import (FriWireError, MEASUREMENT_DTYPE, REMOTE_PORT, command_packet,
                                          decode_command, new_measurement, read_krl, unwrap,
                                          write_measurement)

__all__ = ["FriUdpCounters", "FriUdpEndpoint", "hold_measured_pose", "host_port"]

_RECV_BYTES = 2048  # larger than any FRI datagram: a longer one arrives cut, and is still the wrong size
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux's value; Python 3.11 does not name it
_TIMESPEC = struct.Struct("@ll")  # struct timespec: tv_sec, tv_nsec
_ANCILLARY_BYTES = socket.CMSG_SPACE(_TIMESPEC.size) if hasattr(socket, "CMSG_SPACE") else 64


@dataclass
class FriUdpCounters:
    """Datagrams since the endpoint opened."""

    sent: int = 0  # measurement datagrams handed to the socket
    send_errors: int = 0  # sends the socket refused (buffer full, unreachable)
    received: int = 0  # datagrams read, whatever they held
    accepted: int = 0  # commands returned as a cycle's answer
    wrong_size: int = 0
    wrong_id: int = 0
    late: int = 0  # answers to a cycle before the open one
    duplicate: int = 0  # further answers to the open cycle
    unsent: int = 0  # answers to a cycle not sent yet (or before any measurement)
    invalid: int = 0  # well-formed datagrams whose command CommandPacket.is_valid rejects
    receive_errors: int = 0  # errors the socket reported on reading
    foreign: int = 0  # datagrams from another address than the remote's: ignored, KRL requests included


def host_port(text: str, what: str, *, listen: bool = False) -> tuple[str, int]:
    """``"HOST:PORT"`` as (host, port), a numeric IPv4 address or ``localhost``; ValueError
    naming ``what`` otherwise.  ``listen``: port 0 (any free one) is allowed."""
    host, colon, port = str(text).rpartition(":")
    if not colon or not host:
        raise ValueError(f"{what} {text!r}: expected HOST:PORT, e.g. 127.0.0.1:{REMOTE_PORT}")
    if host != "localhost":
        try:
            socket.inet_aton(host)
            if host.count(".") != 3:
                raise OSError
        except OSError:
            raise ValueError(f"{what} {text!r}: {host!r} is not an IPv4 address") from None
    lowest = 0 if listen else 1
    if not port.isdigit() or not lowest <= int(port) <= 65535:
        raise ValueError(f"{what} {text!r}: port {port!r} is not in {lowest}..65535")
    return ("127.0.0.1" if host == "localhost" else host), int(port)


def hold_measured_pose(m: MeasurementPacket) -> CommandPacket:
    """The values a command's unflagged fields take by default: the measured pose and
    joints, no stiffness, damping 0.7, no added wrench (``CommandPacket.from_measurement``).
    A KRC would use what its KRL program set; pass ``defaults`` to say so."""
    return CommandPacket.from_measurement(m)


class FriUdpEndpoint:
    """The KRC's FRI socket.  ``bind`` is the KRC's own address (port 0: any free
    port), ``remote`` where measurements go (the remote libraries listen on 49938).
    ``defaults(m)`` gives the values of the fields a command leaves unflagged.
    Use as a context manager, or call :meth:`close`."""

    def __init__(self, remote: tuple[str, int] = ("127.0.0.1", REMOTE_PORT),
                 bind: tuple[str, int] = ("127.0.0.1", 0), *,
                 defaults: Callable[[MeasurementPacket], CommandPacket | None] = hold_measured_pose,
                 clock: Callable[[], int] = time.monotonic_ns):
        self.remote = (str(remote[0]), int(remote[1]))
        # the address its datagrams come from ("localhost" as the kernel reports it)
        self._remote_source = (socket.gethostbyname(self.remote[0]), self.remote[1])
        self.defaults = defaults
        self.clock = clock
        self.counters = FriUdpCounters()
        self.krl_to = KrlChannels()  # $FRI_TO_*: sent with every measurement
        self.krl_from: KrlChannels | None = None  # $FRI_FRM_* of the newest well-formed command
        self.last_reject_reason = ""
        self.last_source: tuple[str, int] | None = None  # where the newest datagram came from
        self.last_sent = b""  # the bytes of the last measurement sent
        self.last_accepted = b""  # the bytes of the last command accepted
        self.krl_accepted: KrlChannels | None = None  # $FRI_FRM_* of the last command accepted
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind(bind)
            self._sock.setblocking(False)
        except OSError:
            self._sock.close()
            raise
        # the datagram's bytes, and a structured view on them that write_measurement fills
        self._out_buf = bytearray(new_measurement().tobytes())
        self._out = np.ndarray((), dtype=MEASUREMENT_DTYPE, buffer=self._out_buf)
        self._in_buf = bytearray(_RECV_BYTES)
        self._in = memoryview(self._in_buf)
        self._in_vec = [self._in_buf]
        # Linux stamps each datagram as it arrives (SO_TIMESTAMPNS): the answer's latency is
        # then measured to its arrival, not to when the KRC's loop got round to reading it
        self._kernel_stamps = False
        if sys.platform == "linux":
            try:
                self._sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
                self._kernel_stamps = True
            except OSError:
                pass
        self._open_seq: int | None = None
        self._mode = ControlMode.OTHER
        self._measurement: MeasurementPacket | None = None
        self._defaults: CommandPacket | None = None
        self._command: CommandPacket | None = None
        self._arrival_ns = 0

    # ---------------------------------------------------------------- lifetime
    @property
    def address(self) -> tuple[str, int]:
        """The KRC side's bound (host, port)."""
        return self._sock.getsockname()

    def fileno(self) -> int:
        return self._sock.fileno()

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ cycle
    @property
    def open_seq(self) -> int | None:
        """The cycle of the last measurement sent (None before the first)."""
        return self._open_seq

    @property
    def command(self) -> CommandPacket | None:
        """The open cycle's accepted command, if one has been read."""
        return self._command

    @property
    def arrival_ns(self) -> int:
        """``clock()`` when the accepted command was read (0 with none)."""
        return self._arrival_ns if self._command is not None else 0

    def send(self, m: MeasurementPacket, *, extras: MeasurementExtras | None = None) -> bool:
        """Send ``m`` (with :attr:`krl_to`) and open its cycle: answers to earlier cycles
        are late from now on.  False if the socket refused it (counted)."""
        write_measurement(self._out, m, krl=self.krl_to, extras=extras)
        self._open_seq = int(m.seq)
        self._mode = ControlMode(m.control_mode)
        self._measurement = m
        self._defaults = None  # made from m when a command first needs them (most cycles: once)
        self._command = None
        try:
            self._sock.sendto(self._out_buf, self.remote)
        except OSError:
            self.counters.send_errors += 1
            return False
        self.counters.sent += 1
        self.last_sent = bytes(self._out_buf)
        return True

    def poll(self, timeout_s: float = 0.0) -> CommandPacket | None:
        """Read every datagram waiting (and, with ``timeout_s`` > 0, wait up to that long
        for the open cycle's answer); return the open cycle's accepted command or None."""
        self._drain()
        if self._command is not None or timeout_s <= 0.0:
            return self._command
        deadline = time.monotonic() + timeout_s
        while self._command is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                break
            ready, _, _ = select.select([self._sock], [], [], remaining)
            if ready:
                self._drain()
        return self._command

    def _drain(self) -> None:
        while True:
            try:
                if self._kernel_stamps:
                    n, ancillary, _, source = self._sock.recvmsg_into(self._in_vec, _ANCILLARY_BYTES)
                else:
                    n, source = self._sock.recvfrom_into(self._in_buf)
                    ancillary = ()
            except BlockingIOError:
                return
            except OSError:
                self.counters.receive_errors += 1
                return
            self.counters.received += 1
            self.last_source = source
            if source != self._remote_source:  # (host, port): an AF_INET address
                self.counters.foreign += 1
                self.last_reject_reason = f"a datagram from {source[0]}:{source[1]}, not the remote " \
                                          f"{self._remote_source[0]}:{self._remote_source[1]}"
                continue
            self._take(self._in[:n], self._arrival(ancillary))

    def _arrival(self, ancillary) -> int:
        """When the datagram arrived, on ``clock``: the kernel's stamp (how long it has
        waited in the socket's buffer) taken off now, else now."""
        now = self.clock()
        for level, kind, data in ancillary:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
                sec, nsec = _TIMESPEC.unpack_from(data)
                return now - max(0, time.time_ns() - (sec * 1_000_000_000 + nsec))
        return now

    def _take(self, data: memoryview, arrival_ns: int) -> None:
        c = self.counters
        try:
            rec = decode_command(data)
        except FriWireError as exc:
            if exc.reason == "size":
                c.wrong_size += 1
            else:
                c.wrong_id += 1
            self.last_reject_reason = str(exc)
            return
        self.krl_from = read_krl(rec)
        if self._open_seq is None:
            c.unsent += 1
            self.last_reject_reason = "a command before any measurement was sent"
            return
        seq = unwrap(int(rec["head"]["reflSeqCount"]), self._open_seq)
        if seq > self._open_seq:
            c.unsent += 1
            self.last_reject_reason = f"answer to cycle {seq}, not sent yet (open {self._open_seq})"
            return
        if seq < self._open_seq:
            c.late += 1
            self.last_reject_reason = f"answer to cycle {seq}, after its cycle (open {self._open_seq})"
            return
        if self._command is not None:
            c.duplicate += 1
            self.last_reject_reason = f"duplicate answer to cycle {seq}"
            return
        if self._defaults is None and self.defaults is not None:
            self._defaults = self.defaults(self._measurement)
        cmd = command_packet(rec, seq, self._mode, self._defaults)
        ok, reason = cmd.is_valid()
        if not ok:
            c.invalid += 1
            self.last_reject_reason = reason
            return
        self._command = cmd
        self._arrival_ns = arrival_ns
        self.last_accepted = bytes(data)
        self.krl_accepted = self.krl_from
        c.accepted += 1
        self.last_reject_reason = ""
