"""A cell's KRC speaking FRI 1.0 over UDP: its socket and its KRL program, cycle by cycle.

    krc = UdpKrc(cell, remote=("127.0.0.1", 49938), krl="frilibrary")
    m = cell.begin_cycle()
    krc.send(m)                 # the KRL program's cycle, then the measurement datagram
    ...                         # the remote has until the cycle ends to answer
    krc.take(m)                 # its command, if it came, handed to the link (through its faults)
    cell.end_cycle()

The robot node runs this on the realtime clock (``--wire udp``); a test can run it with
``take(m, timeout_s, latency_ns=...)``, waiting for each answer and taking it to arrive
after a fixed simulated latency, which makes the exchange independent of the host.
What crossed the wire is kept for recording: :attr:`UdpKrc.last_sent` (the measurement's
bytes), :attr:`UdpKrc.last_accepted` (the command's, when ``take`` returned one).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

from robot_sim.cell import RobotCell
from robot_sim.krc.packets import CommandPacket, FriState, MeasurementPacket
from robot_sim.wire.fri_udp import FriUdpEndpoint
from robot_sim.wire.fri_datagrams import REMOTE_PORT
from robot_sim.krc.krl import KrlProgram

__all__ = ["UdpKrc"]


class UdpKrc:
    def __init__(self, cell: RobotCell, remote: tuple[str, int] = ("127.0.0.1", REMOTE_PORT),
                 bind: tuple[str, int] = ("127.0.0.1", 0), *, krl: str = "frilibrary",
                 clock: Callable[[], int] = time.monotonic_ns):
        self.cell = cell
        self.clock = clock
        self.endpoint = FriUdpEndpoint(remote, bind, clock=clock)
        try:
            self.krl = KrlProgram(krl, cell.fri, cell.switch_control_mode, cycle_hz=1e9 / cell.cycle_ns)
        except BaseException:
            self.endpoint.close()
            raise
        # the KRC's checks on a remote's commands (RobotCell.remote_checks)
        cell.remote_checks = True
        self.sent_ns = 0  # clock() when the open cycle's measurement went out (0: it did not)
        self.latency_ns = 0  # of the last command taken

    @property
    def address(self) -> tuple[str, int]:
        return self.endpoint.address

    @property
    def remote(self) -> tuple[str, int]:
        return self.endpoint.remote

    @property
    def last_sent(self) -> bytes:
        return self.endpoint.last_sent

    @property
    def last_accepted(self) -> bytes:
        return self.endpoint.last_accepted

    def close(self) -> None:
        self.endpoint.close()

    def __enter__(self) -> UdpKrc:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def send(self, m: MeasurementPacket) -> bool:
        """The KRL program's cycle, then ``m`` as a datagram, with what the KRL program
        reports; after a close it goes out as OFF.  False if it did not go out (lost by
        the link's fault model, or refused by the socket)."""
        ep, krl = self.endpoint, self.krl
        krl.step(m.seq, ep.krl_from)
        ep.krl_to = krl.krl_to
        wire = dataclasses.replace(m, state=FriState.OFF) if krl.streaming_off else m
        self.sent_ns = 0
        if self.cell.fri.deliver_measurement(m) is None:
            return False
        extras = self.cell.fri_extras()
        # stamped before it goes: a remote on this host can answer before sendto returns
        sent = self.clock()
        if not ep.send(wire, extras=extras):
            return False
        self.sent_ns = sent
        return True

    def answered(self) -> bool:
        """The open cycle's command has come (reads what is waiting on the socket)."""
        return self.endpoint.poll() is not None

    def take(self, m: MeasurementPacket, timeout_s: float = 0.0, *,
             latency_ns: int | None = None) -> CommandPacket | None:
        """The open cycle's command (waiting up to ``timeout_s`` for it), handed to the
        link at the simulated time it arrived (the measurement's stamp plus the measured
        latency, or plus ``latency_ns``: a run that waits for each answer, whatever the
        host's timing), through the link's fault model; None if none came."""
        cmd = self.endpoint.poll(timeout_s)
        if cmd is None or not self.sent_ns:
            return None
        # never negative: the kernel's arrival stamp is carried over to ``clock`` by reading
        # both clocks, which can put an answer a few microseconds before its measurement
        self.latency_ns = max(0, self.endpoint.arrival_ns - self.sent_ns)
        self.cell.deliver(cmd, m.stamp_ns + (self.latency_ns if latency_ns is None else latency_ns))
        return cmd
