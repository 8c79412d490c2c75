"""A Net F/T client for the estimator (``--netft HOST:PORT``), written from WIRE.md.

It reads the counts per force and per torque from the box's ``/netftapi2.xml`` (HTTP),
asks for real-time RDT streaming (``0x1234, 0x0002, 0``: until stopped) from its own UDP
socket, and hands every 36-byte record to ``on_record(msg, recv_ns)`` as the
``ft/wrench`` message it stands for: ``seq`` and ``stamp_ns`` from ``ft_sequence``,
which the testbench's sensor counts from the cell's start, so it is the robot cycle's
(``services/nodes/ft_sensor.py``); the Net F/T status word's saturation bit becomes the
ATI model's out-of-range bit, which is what the estimator acts on.  Records out of order
(``rdt_sequence`` going back) are dropped and counted; a gap is counted as lost.
:meth:`close` sends the stop request.  The client runs on a thread of its own, so the
box may come up after it.
"""

from __future__ import annotations

import select
import socket
import threading
import time
import urllib.request
import xml.etree.ElementTree as ET
from collections.abc import Callable

from robot_sim.cycle import FRI_CYCLE_NS
from robot_sim.wire.netft import NETFT_SATURATION, RDT_HEADER, RDT_RECORD, RDT_REQUEST, RdtCommand
from robot_sim.ati.rdt import AtiStatus
from services.runtime.messages import FT_WRENCH

# the Net F/T word tells saturation (bit 17, which the box also sets for a non-finite
# gauge reading) from any other error: the ATI model's bits the estimator reads for each
_SATURATED = int(AtiStatus.ERROR | AtiStatus.FT_OUT_OF_RANGE)
_INVALID = int(AtiStatus.ERROR)


def read_calibration(host: str, http_port: int, timeout: float = 5.0) -> tuple[float, float]:
    """(counts per force, counts per torque) from the box's /netftapi2.xml."""
    url = f"http://{host}:{http_port}/netftapi2.xml"
    try:
        with urllib.request.urlopen(url, timeout=timeout) as reply:
            root = ET.fromstring(reply.read())
        cpf, cpt = float(root.findtext("cfgcpf")), float(root.findtext("cfgcpt"))
    except (OSError, ET.ParseError, TypeError, ValueError) as exc:
        raise OSError(f"--netft: cannot read the box's calibration from {url}: {exc}") from None
    if not (cpf > 0 and cpt > 0):
        raise OSError(f"--netft: {url} gives counts per force {cpf} and per torque {cpt}; both must be > 0")
    return cpf, cpt


class NetFtStream:
    """Streams from the box at ``address`` (RDT) until closed.  The box may come up after
    the client (the services start together) or go away and come back: the client reads
    the calibration until it gets it, and asks again for the stream whenever it has
    heard nothing for ``RESTART_S``."""

    RESTART_S = 0.5

    def __init__(self, address: tuple[str, int], http_port: int, on_record: Callable, clock: Callable[[], int]):
        self.address = address
        self.http_port = http_port
        self.on_record = on_record
        self.clock = clock
        self.cpf = self.cpt = None
        self.records = self.lost = self.out_of_order = self.garbage = self.requests = 0
        self.last_error = ""
        self._last_rdt = None
        self._asked_again = False  # a new stream was asked for and has not begun yet
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.connect(address)  # the box answers from its RDT port: nothing else gets in
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="netft-client", daemon=True)
        self._thread.start()

    def status(self) -> dict:
        return {"address": f"{self.address[0]}:{self.address[1]}", "records": self.records, "lost": self.lost,
                "out_of_order": self.out_of_order, "garbage": self.garbage, "requests": self.requests,
                "calibrated": self.cpf is not None, "last_error": self.last_error}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        try:
            self._sock.send(RDT_REQUEST.pack(RDT_HEADER, RdtCommand.STOP, 0))
        except OSError:
            pass
        self._sock.close()

    def _run(self) -> None:
        heard = 0.0
        while not self._stop.is_set():
            if self.cpf is None:
                try:
                    self.cpf, self.cpt = read_calibration(self.address[0], self.http_port, timeout=1.0)
                except OSError as exc:
                    self.last_error = str(exc)
                    self._stop.wait(0.2)
                    continue
            now = time.monotonic()
            if now - heard > self.RESTART_S:
                try:
                    self._sock.send(RDT_REQUEST.pack(RDT_HEADER, RdtCommand.REALTIME, 0))
                    self.requests += 1
                    self._last_rdt = None  # a new stream numbers its records from 1 again
                    self._asked_again = True
                except OSError as exc:
                    self.last_error = str(exc)
                heard = now
            ready, _, _ = select.select([self._sock], [], [], 0.1)
            if not ready:
                continue
            try:
                data = self._sock.recv(2048)
            except OSError as exc:  # the box not up (yet): ICMP port unreachable
                self.last_error = str(exc)
                continue
            recv_ns = self.clock()
            heard = time.monotonic()
            if not data or len(data) % RDT_RECORD.size:
                self.garbage += 1
                continue
            for record in RDT_RECORD.iter_unpack(data):
                self._take(record, recv_ns)

    def _take(self, record, recv_ns: int) -> None:
        rdt, ft, status = record[:3]
        counts = record[3:]
        if self._last_rdt is not None:
            step = (rdt - self._last_rdt) & 0xFFFFFFFF
            if step == 0 or step > 0x7FFFFFFF:
                if not self._asked_again:
                    self.out_of_order += 1
                    return
                # the stream asked for again begins, numbered from 1 again: the records before
                # it were the old stream's, still on their way when the request went out (after
                # a stall of RESTART_S), not out of order
                self._asked_again = False
            else:
                self.lost += step - 1
        if rdt == 1:
            self._asked_again = False  # the new stream's first: what follows numbers on from it
        self._last_rdt = rdt
        self.records += 1
        model_status = 0
        if status:
            model_status = _SATURATED if status & NETFT_SATURATION else _INVALID
        seq = int(ft)
        wrench = [c / self.cpf for c in counts[:3]] + [c / self.cpt for c in counts[3:]]
        msg = FT_WRENCH.pack(seq=seq, stamp_ns=(seq - 1) * FRI_CYCLE_NS, sent_ns=recv_ns, rdt_sequence=int(rdt),
                             ft_sequence=seq, status=model_status, counts=list(counts), counts_per_force=self.cpf,
                             counts_per_torque=self.cpt, wrench=wrench)[1]
        self.on_record(msg, recv_ns)

