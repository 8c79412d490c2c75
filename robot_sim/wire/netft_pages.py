"""The Net F/T box's TCP side: the XML pages it serves over HTTP (``/netftapi2.xml``,
``/netftcalapi.xml``) and the calibration channel's READCALINFO reply (TCP 49151), and
the threading servers that answer them for a :class:`robot_sim.wire.netft.NetFtBox`."""

from __future__ import annotations

import http.server
import socket
import socketserver
import struct
import threading
import time
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from robot_sim.ati.sensor import AtiConfig

RDT_HEADER = 0x1234  # the first word of every RDT request and of the calibration reply
_CALINFO_REQUEST_SIZE = 20
_CALINFO_REPLY = struct.Struct(">HBBII6H")
_FORCE_UNIT_N = 2
_TORQUE_UNIT_NM = 3


class ServedBox(Protocol):
    """What the pages and servers read of the box (``robot_sim.wire.netft.NetFtBox``, which
    imports this module for its servers)."""

    config: AtiConfig
    rdt_buffer_size: int
    product_name: str
    calibration_name: str

    def count(self, what: str) -> None: ...


def netftapi2_xml(box: ServedBox) -> str:
    """The body of ``/netftapi2.xml``."""
    c = box.config
    rate = round(1.0 / c.sample_period_s)
    return ("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<netft>\n"
            f"<prodname>{box.product_name}</prodname>\n"
            f"<cfgcpf>{c.counts_per_force}</cfgcpf>\n<cfgcpt>{c.counts_per_torque}</cfgcpt>\n"
            "<scfgfu>N</scfgfu>\n<scfgtu>Nm</scfgtu>\n"
            f"<comrdtrate>{rate}</comrdtrate>\n<comrdtbsiz>{box.rdt_buffer_size}</comrdtbsiz>\n"
            "</netft>\n")

def netftcalapi_xml(box: ServedBox) -> str:
    """The body of ``/netftcalapi.xml``."""
    c = box.config
    return ("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<netftCalibration>\n"
            f"<calpn>{box.calibration_name}</calpn>\n<calfu>N</calfu>\n<caltu>Nm</caltu>\n"
            f"<calcpf>{c.counts_per_force}</calcpf>\n<calcpt>{c.counts_per_torque}</calcpt>\n"
            "</netftCalibration>\n")

def calibration_info(config: AtiConfig) -> bytes:
    """The 24-byte READCALINFO reply of TCP 49151."""
    c = config
    return _CALINFO_REPLY.pack(RDT_HEADER, _FORCE_UNIT_N, _TORQUE_UNIT_NM, c.counts_per_force,
                               c.counts_per_torque, *([1] * 6))


class _Connections:
    """A threading server's open connections, cut at close: a client that trickles a byte a
    second would otherwise hold its handler thread (and the box's close, which joins it)
    for as long as it likes."""

    daemon_threads = True  # a handler that does not end is not waited for at exit
    timeout = 0  # handle_request() is called only when a connection is waiting
    _CLOSE_JOIN_S = 1.0

    def _track(self) -> None:
        self._open: set = set()
        self._handlers: list[threading.Thread] = []
        self._open_lock = threading.Lock()
        self._closing = False

    def process_request(self, request, client_address):
        thread = threading.Thread(target=self.process_request_thread, args=(request, client_address),
                                  name=f"{type(self).__name__} {client_address[0]}:{client_address[1]}", daemon=True)
        with self._open_lock:
            self._open.add(request)
            self._handlers = [t for t in self._handlers if t.is_alive()] + [thread]
        thread.start()

    def shutdown_request(self, request):
        with self._open_lock:
            self._open.discard(request)
        super().shutdown_request(request)

    def handle_error(self, request, client_address):
        if not self._closing:  # a connection cut at close is not an error of the client's
            super().handle_error(request, client_address)

    def server_close(self):
        with self._open_lock:
            self._closing = True
            open_now, handlers = list(self._open), list(self._handlers)
        for sock in open_now:  # the handlers' reads end at once
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        super(socketserver.ThreadingMixIn, self).server_close()  # the listening socket
        deadline = time.monotonic() + self._CLOSE_JOIN_S
        for thread in handlers:
            thread.join(max(0.0, deadline - time.monotonic()))


class PagesServer(_Connections, http.server.ThreadingHTTPServer):
    """The box's web server; requests are accepted by the box's I/O thread."""

    def __init__(self, address, box: ServedBox):
        self.box = box
        self._track()
        super().__init__(address, _XmlHandler)


class _XmlHandler(http.server.BaseHTTPRequestHandler):
    timeout = 2.0
    server_version = "NetFtSim/1.0"

    def do_GET(self):  # the name http.server calls
        path = self.path.split("?", 1)[0]
        box = self.server.box
        pages = {"/netftapi2.xml": netftapi2_xml, "/netftcalapi.xml": netftcalapi_xml}
        if path not in pages:
            self.send_error(404)
            return
        self.server.box.count("http_requests")
        body = pages[path](box).encode()
        self.send_response(200)
        self.send_header("Content-Type", "text/xml")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def send_error(self, code, message=None, explain=None):  # the signature http.server calls
        # a missing page, a malformed request line, a method the box has not (garbage)
        self.server.box.count("http_refused")
        super().send_error(code, message, explain)

    def log_message(self, format, *args):  # the signature http.server calls
        pass


class CalibrationServer(_Connections, socketserver.ThreadingTCPServer):
    """The calibration channel (TCP 49151); requests are accepted by the box's I/O thread."""

    allow_reuse_address = True

    def __init__(self, address, box: ServedBox):
        self.box = box
        self._track()
        super().__init__(address, _CalibrationHandler)


class _CalibrationHandler(socketserver.BaseRequestHandler):
    """READCALINFO requests on one connection until the client closes it (or 2 s idle)."""

    def handle(self):
        self.request.settimeout(2.0)
        while True:
            try:
                data = _receive_exactly(self.request, _CALINFO_REQUEST_SIZE)
            except OSError:
                return
            if data is None:
                return  # closed
            if data[0] != 0x01:
                self.server.box.count("calibration_refused")
                return  # a command this box does not know (READFT): hang up
            self.server.box.count("calibration_requests")
            try:
                self.request.sendall(calibration_info(self.server.box.config))
            except OSError:
                return


def _receive_exactly(sock: socket.socket, n: int) -> bytes | None:
    parts, got = [], 0
    while got < n:
        chunk = sock.recv(n - got)
        if not chunk:
            return None
        parts.append(chunk)
        got += len(chunk)
    return b"".join(parts)
