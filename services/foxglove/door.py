"""The live view's front door: it lets in viewers that offer only ``foxglove.websocket.v1``.

foxglove-sdk's server names its protocol ``foxglove.sdk.v1`` and answers HTTP 400 to a
client that offers only the older name ``foxglove.websocket.v1``.  Foxglove Studio 1.48,
the last open-source release, offers only that name; so did Lichtblick until December
2025, and so do the ws-protocol client libraries.  Foxglove says the two names stand for one wire
format (foxglove-sdk discussion 1131), and Lichtblick's fix added the new name and changed
nothing else (lichtblick PR 819).  So the door rewrites only the name, in the HTTP upgrade,
both ways.  After that it copies bytes: the frames are the SDK server's own, not parsed.
A client that offers ``foxglove.sdk.v1`` passes through untouched.
"""

from __future__ import annotations

import socket
import threading

OLD_NAME = "foxglove.websocket.v1"
SDK_NAME = "foxglove.sdk.v1"
PROTOCOL_HEADER = b"sec-websocket-protocol"
MAX_HEAD_BYTES = 16384  # an HTTP upgrade is a few hundred bytes
HEAD_TIMEOUT_S = 10.0


def read_head(sock: socket.socket) -> tuple[bytes, bytes]:
    """An HTTP head up to its blank line, and what came after it; raises ConnectionError
    on a head that does not end within MAX_HEAD_BYTES or a peer that closes first."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(4096)
        if not chunk:
            raise ConnectionError("closed before the end of the HTTP head")
        data += chunk
        if len(data) > MAX_HEAD_BYTES and b"\r\n\r\n" not in data:
            raise ConnectionError(f"HTTP head longer than {MAX_HEAD_BYTES} bytes")
    end = data.index(b"\r\n\r\n") + 4
    return data[:end], data[end:]


def _protocol_lines(lines: list[bytes]):
    """(index, header name, protocol names) of each Sec-WebSocket-Protocol line of a head's lines."""
    for i, line in enumerate(lines[1:], start=1):
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == PROTOCOL_HEADER:
            yield i, name, [p.strip().decode("latin-1") for p in value.split(b",") if p.strip()]


def offered_protocols(head: bytes) -> list[str]:
    return [p for _, _, names in _protocol_lines(head.split(b"\r\n")) for p in names]


def rename_protocol(head: bytes, old: str, new: str) -> bytes:
    """The head with ``old`` replaced by ``new`` in its Sec-WebSocket-Protocol lines only."""
    lines = head.split(b"\r\n")
    for i, name, names in list(_protocol_lines(lines)):
        lines[i] = name + b": " + ", ".join(new if p == old else p for p in names).encode("latin-1")
    return b"\r\n".join(lines)


def pump(source: socket.socket, sink: socket.socket) -> None:
    """Copy bytes until ``source`` ends, then end ``sink``'s sending side."""
    try:
        while chunk := source.recv(65536):
            sink.sendall(chunk)
    except OSError:
        pass
    finally:
        try:
            sink.shutdown(socket.SHUT_WR)
        except OSError:
            pass


class SubprotocolDoor:
    """Listens on ``host:port`` (0: any free port, then in ``.port``) and joins each client
    to the SDK's server on ``127.0.0.1:upstream_port``."""

    def __init__(self, host: str, port: int, upstream_port: int):
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.listener = socket.create_server((host, port), family=family)
        self.port = self.listener.getsockname()[1]
        self.upstream_port = upstream_port
        self.renamed = 0  # connections let in under the old name
        self.refused = 0  # connections that ended before their upgrade was through
        self._lock = threading.Lock()
        self._open: set[socket.socket] = set()
        self._closed = False
        threading.Thread(target=self._accept, name="foxglove-door", daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return  # closed
            threading.Thread(target=self._join, args=(client,), name="foxglove-door-client", daemon=True).start()

    def _track(self, *socks: socket.socket) -> bool:
        with self._lock:
            if self._closed:
                return False
            self._open.update(socks)
            return True

    def _join(self, client: socket.socket) -> None:
        upstream = None
        try:
            client.settimeout(HEAD_TIMEOUT_S)
            request, rest = read_head(client)
            offered = offered_protocols(request)
            rename = SDK_NAME not in offered and OLD_NAME in offered
            if rename:
                request = rename_protocol(request, OLD_NAME, SDK_NAME)
            upstream = socket.create_connection(("127.0.0.1", self.upstream_port), timeout=HEAD_TIMEOUT_S)
            if not self._track(client, upstream):
                raise ConnectionError("the door is closed")
            upstream.sendall(request + rest)
            response, rest = read_head(upstream)
            if rename:
                response = rename_protocol(response, SDK_NAME, OLD_NAME)
                with self._lock:
                    self.renamed += 1
            client.sendall(response + rest)
            client.settimeout(None)
            upstream.settimeout(None)
        except OSError:  # ConnectionError, a timeout, the SDK server gone
            with self._lock:
                self.refused += 1
            for sock in (client, upstream):
                if sock is not None:
                    sock.close()
            return
        back = threading.Thread(target=pump, args=(upstream, client), name="foxglove-door-down", daemon=True)
        back.start()
        pump(client, upstream)
        back.join()
        with self._lock:
            self._open.difference_update((client, upstream))
        client.close()
        upstream.close()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            socks = list(self._open)
        try:
            self.listener.shutdown(socket.SHUT_RDWR)  # wakes the accept (close alone does not, on Linux)
        except OSError:
            pass
        self.listener.close()
        for sock in socks:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
