"""The simulated ATI box on the network: :class:`NetFtBox` speaks Net F/T.

:class:`robot_sim.ati.sensor.AtiSensor` makes the records an ATI Net F/T would send; this module
puts them on the wire the way the real box does, so lab software written for a Net F/T
connects to the simulation unchanged.  The box is fed, not clocked: whoever runs the
sensor's cycle calls :meth:`NetFtBox.publish` with every :class:`~robot_sim.ati.rdt.RdtRecord`,
and the box sends it to the clients that asked for a stream.  No sensor model, no physics
and no wall clock inside.

Channels (one box per address: 127.0.0.1 by default, 127.0.0.x for more boxes on one
machine, any IPv4 address of the machine to be reached from another; ports configurable,
0 picks a free one; ``tap(peer, datagram)`` sees every RDT datagram sent, for recording)
----------------------------------------------------------------------------------------
* **RDT, UDP 49152**, big-endian.  Request, 8 bytes: ``u16 0x1234, u16 command, u32
  sample count`` (0 = until stopped, otherwise that many records, then the stream ends).
  Commands: 0x0000 stop, 0x0002 real-time streaming (one 36-byte record per datagram),
  0x0003 buffered streaming (``rdt_buffer_size`` records per datagram, the last one of a
  count-limited stream possibly shorter), 0x0041 reset latched threshold conditions (this
  box has no threshold monitoring: acknowledged, nothing changes), 0x0042 software bias.
  Anything else (a malformed request, the multi-unit command 0x0004, which the channel
  description does not ask for) is counted in :attr:`NetFtStats.ignored` and ignored.
  Replies go from the box's UDP port to the request's source address and port (clients
  ``connect()`` their socket and drop anything else).  Each requester has its own stream;
  a new start from the same requester replaces it.  Four streams at most, first come first
  served: a start from a fifth requester is refused (:attr:`NetFtStats.refused`), so a
  stranger cannot cut a stream the box already serves.  A client that died without a stop
  request does not hold its place: on Linux the box asks for the network's errors
  (``IP_RECVERR``), and the ICMP "port unreachable" its next record draws ends that stream
  (:attr:`NetFtStats.unreachable`).  ATI's manual, as summarised in WIRE.md, does not say
  how many clients a real box streams to or what it does with more; these are this box's
  rules, chosen so that a lab's client keeps its stream.
* **HTTP, TCP 80**: ``GET /netftapi2.xml`` (``prodname``, ``cfgcpf``, ``cfgcpt``,
  ``scfgfu``, ``scfgtu``, each exactly once, no DOCTYPE: what pynetft 2.1.3 parses, plus
  ``comrdtrate`` and ``comrdtbsiz``) and ``GET /netftcalapi.xml`` (root
  ``netftCalibration``: ``calpn``, ``calfu``, ``caltu``, ``calcpf``, ``calcpt``).
* **Calibration, TCP 49151** ("READCALINFO"): request 20 bytes, 0x01 then 19 zeros; reply
  24 bytes, ``u16 0x1234, u8 force unit (2 = N), u8 torque unit (3 = N·m), u32 counts per
  force, u32 counts per torque, u16 scale factors[6]``.  The header value and the scale
  factors (all 1) are ASSUMPTIONS: no source at hand gives a real box's values.

Record fields
-------------
* ``rdt_sequence`` numbers the records of one stream, from 1 (it starts again at every
  start request); the sensor's own rdt_sequence is not sent.  A bias request does not
  restart it: pynetft sends bias then start, and a record sent between the two would
  otherwise carry the same rdt_sequence as the new stream's first, which pynetft drops as
  a duplicate (seen in this project's tests when bias restarted it too).
* ``ft_sequence`` is the sensor's (its internal 1 kHz sample counter), so a record on the
  wire can be matched with the simulated one.  It must only increase (pynetft counts a
  repeat or a step back as a fault): a published record whose ft_sequence does not advance
  on the last one is not sent (:attr:`NetFtStats.stale`); one that steps back (a new
  sensor model, counting from 1 again) is renumbered to continue from the last one sent.
  Gaps (samples the sensor's caller skipped) stay gaps.
* ``status``: with ``status_layout="netft"`` (default) the model's :class:`AtiStatus`
  word is translated into the Net F/T system status bits lab software decodes: 0 stays 0;
  a saturated axis, the out-of-range flag or a non-finite input becomes bit 31 (error
  summary) + bit 17 ("transducer saturation or A/D error", 0x00020000; bit layout as
  decoded by netft-cpp, pynetft's core, ``test/test_status.cpp``); any other bit becomes
  bit 31 alone.  The model's own bits 8-14 and 30 would read as analog-board and CPU/RAM
  errors there.  ``status_layout="model"`` sends the model's word unchanged (per-axis
  saturation bits for software that knows :mod:`robot_sim.ati.sensor`).
* ``Fx..Tz``: the sensor's int32 counts, minus the box's bias (below).

Bias (0x0042)
-------------
With ``on_bias=None`` the box biases itself, as the Net F/T does: the next published
record becomes the offset subtracted from every later one (so that record reads exactly
0), for every client, until the box is closed; the sensor model is not touched.  With
``on_bias=callable`` the box only calls it (from its I/O thread) and sends the counts as
they come: the owner tares the sensor model (``AtiSensor.tare``, under the lock that
guards its cycle), so the box and any other consumer of the model see the same bias.

Threads: :meth:`publish` sends from the caller's thread (the sensor cycle); one I/O thread
waits in ``select`` on the UDP socket, both TCP listeners and a wake-up pipe (no polling),
HTTP and calibration connections are served on short-lived threads.  Everything the two
sides share is behind one lock.  :meth:`close` stops and joins all of it: it cuts the
connections still open (a client trickling a byte at a time holds none of it), so it
returns within about a second whatever the clients do.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import os
import selectors
import socket
import socketserver
import struct
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from robot_sim.ati.rdt import SATURATION_BITS, AtiStatus, RdtRecord
from robot_sim.wire.netft_pages import RDT_HEADER, CalibrationServer, PagesServer

if TYPE_CHECKING:
    from robot_sim.ati.sensor import AtiConfig

__all__ = [
    "NETFT_ERROR",
    "NETFT_SATURATION",
    "RDT_HEADER",
    "RDT_RECORD",
    "RDT_REQUEST",
    "NetFtBox",
    "NetFtStats",
    "RdtCommand",
    "netft_status",
]

RDT_PORT = 49152
CALIBRATION_PORT = 49151
HTTP_PORT = 80


class RdtCommand:
    """The RDT request commands the box answers."""

    STOP = 0x0000
    REALTIME = 0x0002
    BUFFERED = 0x0003
    RESET_THRESHOLD_LATCH = 0x0041
    SET_SOFTWARE_BIAS = 0x0042


NETFT_ERROR = 0x80000000
"""Net F/T status bit 31, the error summary."""
NETFT_SATURATION = 0x00020000
"""Net F/T status bit 17, "transducer saturation or A/D error"."""

RDT_REQUEST = struct.Struct(">HHI")  # header 0x1234, command, sample count
RDT_RECORD = RdtRecord._WIRE  # one 36-byte record: rdt_sequence, ft_sequence, status, counts
_RECORD_TAIL = struct.Struct(">2I6i")  # ft_sequence, status, counts: the same for every stream
_RDT_SEQUENCE = struct.Struct(">I")
_UINT32 = 0xFFFFFFFF
_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1
# streams at once; a start request beyond that is refused (a dead client's stream ends on
# the ICMP error its records draw, so crashed clients do not lock new ones out)
_MAX_STREAMS = 4
# Linux: ICMP errors of an unconnected UDP socket are queued for recvmsg(MSG_ERRQUEUE) with
# the original destination, the client that is gone (ip(7))
_IP_RECVERR = getattr(socket, "IP_RECVERR", 11)
_MSG_ERRQUEUE = getattr(socket, "MSG_ERRQUEUE", 0x2000)
_SATURATION_CAUSES = int(AtiStatus.FT_OUT_OF_RANGE | AtiStatus.INPUT_NONFINITE) | sum(int(b) for b in SATURATION_BITS)


def netft_status(model_status: int) -> int:
    """The Net F/T system status word for an :class:`AtiStatus` word (module docstring)."""
    if model_status == 0:
        return 0
    if model_status & _SATURATION_CAUSES:
        return NETFT_ERROR | NETFT_SATURATION
    return NETFT_ERROR


@dataclass
class NetFtStats:
    """What the box has done since it was served (:meth:`NetFtBox.stats` returns a copy)."""

    published: int = 0
    """Records handed to :meth:`NetFtBox.publish`."""
    stale: int = 0
    """Published records not sent because their ft_sequence did not advance."""
    records_sent: int = 0
    """Records sent, summed over the streams."""
    datagrams_sent: int = 0
    requests: int = 0
    """Well-formed RDT requests received."""
    ignored: int = 0
    """RDT datagrams ignored: malformed or an unknown command."""
    http_requests: int = 0
    """HTTP requests answered with a page."""
    http_refused: int = 0
    """HTTP requests that were no GET of a page the box has (404, 400, 501: garbage included)."""
    calibration_requests: int = 0
    """READCALINFO requests answered on TCP 49151."""
    calibration_refused: int = 0
    """Connections to TCP 49151 closed on a request that was not READCALINFO."""
    refused: int = 0
    """Start requests refused: four streams were running, none of them the requester's."""
    unreachable: int = 0
    """Streams ended because the network said their client is gone (ICMP port unreachable)."""
    biases: int = 0
    streams: int = 0
    """Streams running now."""


def _check_ports(**ports: int | None) -> None:
    """Each a port number, 0 to bind a free one; None (the TCP channels only) leaves it out."""
    for name, port in ports.items():
        if port is None and name != "rdt_port":
            continue
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"{name} must be a port number 0..65535, got {port!r}")


def _check_page_names(**names: str) -> None:
    """Names the XML pages carry as they are: no markup in them."""
    for name, text in names.items():
        if not isinstance(text, str) or not text.strip() or len(text) > 128 or any(c in text for c in "<>&"):
            raise ValueError(f"{name} must be 1..128 characters without <, > or &, got {text!r}")


@dataclass
class _Stream:
    buffered: bool
    remaining: int  # records still to send; -1: until stopped
    next_rdt: int = 1
    pending: list[bytes] = dataclasses.field(default_factory=list)  # buffered records not yet sent


class NetFtBox:
    """A Net F/T box on ``address`` that sends what :meth:`publish` is given.

    ``config`` gives the calibration (counts per force and torque, sample rate).  Ports:
    ``rdt_port`` (UDP), ``http_port`` and ``calibration_port`` (TCP, ``None`` to leave
    that channel out); 0 binds a free port, read back from the attribute after
    :meth:`serve`.  Use as a context manager, or :meth:`serve` then :meth:`close`.
    """

    def __init__(
        self,
        config: AtiConfig | None = None,
        *,
        address: str = "127.0.0.1",
        rdt_port: int = RDT_PORT,
        http_port: int | None = HTTP_PORT,
        calibration_port: int | None = CALIBRATION_PORT,
        rdt_buffer_size: int = 10,
        status_layout: Literal["netft", "model"] = "netft",
        on_bias: Callable[[], None] | None = None,
        tap: Callable[[tuple[str, int], bytes], None] | None = None,
        product_name: str = "Net F/T (robot_sim, simulated)",
        calibration_name: str = "SI-290-10",
    ) -> None:
        # the sensor model's module (numba, its kernels) only where a box is made: a reader
        # of the wire imports this module for its layouts alone
        from robot_sim.ati.sensor import AtiConfig

        self.config = AtiConfig.mini45() if config is None else config
        if not isinstance(self.config, AtiConfig):
            raise TypeError(f"config must be an AtiConfig, got {type(self.config).__name__}")
        try:
            ip = ipaddress.IPv4Address(address)
        except ValueError:
            raise ValueError(f"address must be an IPv4 address, got {address!r}") from None
        _check_ports(rdt_port=rdt_port, http_port=http_port, calibration_port=calibration_port)
        if isinstance(rdt_buffer_size, bool) or not isinstance(rdt_buffer_size, int) or not 1 <= rdt_buffer_size <= 40:
            # 40 records of 36 bytes keep a datagram under a 1500-byte Ethernet MTU
            raise ValueError(f"rdt_buffer_size must be an integer 1..40, got {rdt_buffer_size!r}")
        if status_layout not in ("netft", "model"):
            raise ValueError(f"status_layout must be 'netft' or 'model', got {status_layout!r}")
        if on_bias is not None and not callable(on_bias):
            raise TypeError("on_bias must be callable or None")
        if tap is not None and not callable(tap):
            raise TypeError("tap must be callable or None")
        _check_page_names(product_name=product_name, calibration_name=calibration_name)
        self.address = str(ip)
        self.rdt_port = rdt_port
        self.http_port = http_port
        self.calibration_port = calibration_port
        self.rdt_buffer_size = rdt_buffer_size
        self.status_layout = status_layout
        self.product_name = product_name
        self.calibration_name = calibration_name
        self._on_bias = on_bias
        self._tap = tap

        self._lock = threading.Lock()
        self._streams: dict[tuple[str, int], _Stream] = {}
        self._stats = NetFtStats()
        self._last_ft: int | None = None  # ft_sequence of the last record sent, as the sensor numbered it
        self._ft_shift = 0  # added to the sensor's ft_sequence (after a step back)
        self._bias_armed = False
        self._send_failed = False  # a send raised: look at the network's errors
        self._bias = np.zeros(6, dtype=np.int64)
        self._biased = False

        self._udp: socket.socket | None = None
        self._servers: list[socketserver.BaseServer] = []
        self._wake: tuple[int, int] | None = None
        self._thread: threading.Thread | None = None
        self._state = "new"  # new -> serving -> closed

    # -- lifetime -------------------------------------------------------------------

    def serve(self) -> NetFtBox:
        """Bind every channel and start the I/O thread; returns the box.

        Raises ``OSError`` if a port is taken (nothing stays bound then)."""
        if self._state != "new":
            raise RuntimeError(f"a NetFtBox is served once; this one is {self._state}")
        try:
            udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._udp = udp
            udp.bind((self.address, self.rdt_port))
            self.rdt_port = udp.getsockname()[1]
            udp.setblocking(False)  # one I/O thread reads it when select says; publish sends
            if sys.platform == "linux":
                udp.setsockopt(socket.IPPROTO_IP, _IP_RECVERR, 1)
            if self.http_port is not None:
                server = PagesServer((self.address, self.http_port), self)
                self._servers.append(server)
                self.http_port = server.server_address[1]
            if self.calibration_port is not None:
                server = CalibrationServer((self.address, self.calibration_port), self)
                self._servers.append(server)
                self.calibration_port = server.server_address[1]
            self._wake = os.pipe()
        except BaseException:
            self._release()
            self._state = "closed"
            raise
        self._state = "serving"
        self._thread = threading.Thread(target=self._run, name=f"netft-{self.address}", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop streaming, close every socket and join the threads.  Idempotent."""
        if self._state == "serving":
            self._state = "closed"
            os.write(self._wake[1], b"x")
            self._thread.join()
        self._state = "closed"
        with self._lock:
            self._streams.clear()
        self._release()

    def _release(self) -> None:
        for server in self._servers:
            server.server_close()  # joins the connection threads (their sockets time out)
        self._servers = []
        if self._udp is not None:
            self._udp.close()
            self._udp = None
        if self._wake is not None:
            for fd in self._wake:
                os.close(fd)
            self._wake = None

    def __enter__(self) -> NetFtBox:
        """Serves the box unless :meth:`serve` already did."""
        return self if self._state == "serving" else self.serve()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def serving(self) -> bool:
        return self._state == "serving"

    def count(self, what: str) -> None:
        """One more of a :class:`NetFtStats` counter (from a connection's thread)."""
        with self._lock:
            setattr(self._stats, what, getattr(self._stats, what) + 1)

    def stats(self) -> NetFtStats:
        with self._lock:
            return dataclasses.replace(self._stats, streams=len(self._streams))

    # -- the sensor side ------------------------------------------------------------

    def publish(self, record: RdtRecord) -> int:
        """Send one sensor record to every stream; returns how many streams got it.

        Called from the sensor's cycle with each record, in order.  Cheap when nobody
        streams (a sequence check).  A record that does not advance ft_sequence is not
        sent (module docstring)."""
        with self._lock:
            stats = self._stats
            stats.published += 1
            ft = int(record.ft_sequence)
            if self._last_ft is not None:
                step = (ft - self._last_ft) & _UINT32
                if step == 0:
                    stats.stale += 1
                    return 0
                if step > _UINT32 // 2:  # behind the last one: a restarted sensor continues the count
                    self._ft_shift = (self._ft_shift + self._last_ft + 1 - ft) & _UINT32
            self._last_ft = ft
            counts = record.counts
            if self._bias_armed:
                self._bias[:] = counts
                self._bias_armed, self._biased = False, True
            if self._biased:
                counts = np.clip(counts.astype(np.int64) - self._bias, _INT32_MIN, _INT32_MAX)
            status = int(record.status)
            if self.status_layout == "netft":
                status = netft_status(status)
            if not self._streams:
                return 0
            tail = _RECORD_TAIL.pack((ft + self._ft_shift) & _UINT32, status, *counts.tolist())
            records = datagrams = 0
            finished = []
            for peer, stream in self._streams.items():
                data = _RDT_SEQUENCE.pack(stream.next_rdt) + tail
                stream.next_rdt = (stream.next_rdt + 1) & _UINT32
                records += 1
                if stream.remaining > 0:
                    stream.remaining -= 1
                    if stream.remaining == 0:
                        finished.append(peer)
                if stream.buffered:
                    stream.pending.append(data)
                    if len(stream.pending) < self.rdt_buffer_size and stream.remaining != 0:
                        continue
                    data = b"".join(stream.pending)
                    stream.pending.clear()
                sent = self._send(data, peer)
                datagrams += sent
                if sent and self._tap is not None:
                    self._tap(peer, data)
            for peer in finished:
                del self._streams[peer]
            if self._send_failed:
                self._end_unreachable()
            stats.records_sent += records
            stats.datagrams_sent += datagrams
            return records

    def _send(self, data: bytes, peer: tuple[str, int]) -> int:
        udp = self._udp
        if udp is None:
            return 0
        for _ in range(2):
            try:
                udp.sendto(data, peer)
                return 1
            except ConnectionRefusedError:
                # an earlier record's ICMP error, reported by this send, which it stopped
                # (the error is cleared by being reported): send again
                self._send_failed = True
            except OSError:  # a full buffer: UDP, the record is lost as on the wire
                self._send_failed = True
                return 0
        return 0

    def _end_unreachable(self) -> None:
        """End the streams whose client the network says is gone (the ICMP errors queued
        since the last look); call with the lock held."""
        self._send_failed = False
        udp = self._udp
        while udp is not None:
            try:
                _, _, _, peer = udp.recvmsg(64, 512, _MSG_ERRQUEUE)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # no error queue here (not Linux), or the socket is closed
                return
            if peer is not None and self._streams.pop(peer, None) is not None:
                self._stats.unreachable += 1

    # -- the network side -----------------------------------------------------------

    def _run(self) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self._udp, selectors.EVENT_READ, self._on_rdt)
            for server in self._servers:
                selector.register(server.socket, selectors.EVENT_READ, server.handle_request)
            selector.register(self._wake[0], selectors.EVENT_READ, None)
            while True:
                for key, _ in selector.select():
                    if key.data is None:
                        return
                    key.data()

    def _on_rdt(self) -> None:
        try:
            data, peer = self._udp.recvfrom(2048)
        except BlockingIOError:
            return
        except OSError:  # the socket's pending ICMP error (IP_RECVERR): whose client is gone
            with self._lock:
                self._end_unreachable()
            return
        bias = False
        with self._lock:
            stats = self._stats
            if len(data) != RDT_REQUEST.size:
                stats.ignored += 1
                return
            header, command, count = RDT_REQUEST.unpack(data)
            known = (RdtCommand.STOP, RdtCommand.REALTIME, RdtCommand.BUFFERED,
                     RdtCommand.RESET_THRESHOLD_LATCH, RdtCommand.SET_SOFTWARE_BIAS)
            if header != RDT_HEADER or command not in known:
                stats.ignored += 1
                return
            if (command in (RdtCommand.REALTIME, RdtCommand.BUFFERED) and peer not in self._streams
                    and len(self._streams) >= _MAX_STREAMS):
                self._end_unreachable()  # a place held by a client that is gone is free
                if len(self._streams) >= _MAX_STREAMS:
                    stats.refused += 1
                    return
            stats.requests += 1
            if command == RdtCommand.STOP:
                self._streams.pop(peer, None)
            elif command in (RdtCommand.REALTIME, RdtCommand.BUFFERED):
                self._streams[peer] = _Stream(buffered=command == RdtCommand.BUFFERED,
                                              remaining=count if count else -1)
            elif command == RdtCommand.SET_SOFTWARE_BIAS:
                stats.biases += 1
                bias = self._on_bias is not None
                if not bias:
                    self._bias_armed = True
        if bias:
            self._on_bias()
