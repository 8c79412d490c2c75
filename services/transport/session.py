"""Zenoh session configuration shared by every service (one helper, as zenoh-python's examples do).

Embedded default: a peer on loopback, multicast scouting off, listening on its
own ``tcp/127.0.0.1:0`` and connecting to the endpoints given (the runner's):
Zenoh peers do not relay for one another, so every peer listens and gossip
links them directly (DESIGN.md).  ``--mode client --connect tcp/HOST:PORT``
joins a Zenoh router instead (docker-compose).  ``--cfg KEY:VALUE`` sets any
other Zenoh configuration key (a misspelt key is refused by Zenoh); the flags
themselves are parsed in ``services.cli.zenoh_flags``.

Zenoh's configuration takes almost any endpoint (``tcp/127.0.0.1:99999``,
``foo/bar``) and a client or peer then retries it for ever: ``check_endpoint``
refuses one that cannot work before anything opens, and ``ZenohOptions.config``
checks every endpoint with it (an ``EndpointError``, a ValueError naming the
flag, the endpoint and what is wrong with it).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass

import zenoh

# the link protocols this Zenoh carries: those addressed HOST:PORT, and a Unix socket's path
IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
# Zenoh's own default port: the router listens on it (etar-bench router, docker-compose.yml's
# ZENOH_PORT default) and the examples name it
ZENOH_PORT = 7447
PATH_PROTOCOLS = ("unixsock-stream",)
_HOST = re.compile(r"\[[0-9A-Fa-f:.%\w]+\]|[A-Za-z0-9._-]+")


class EndpointError(ValueError):
    """An endpoint that cannot be one: ``str()`` is ``"<flag> <endpoint>: <problem>"``."""

    def __init__(self, flag: str, endpoint: str, problem: str):
        super().__init__(f"{flag} {endpoint}: {problem}")
        self.flag, self.endpoint, self.problem = flag, endpoint, problem


def check_endpoint(endpoint: str, flag: str = "--connect", *, listen: bool = False) -> str:
    """``endpoint`` if it is a Zenoh endpoint this program can use, else EndpointError naming
    ``flag``: ``<protocol>/<address>[?<metadata>][#<config>]``, the protocol one of
    ``IP_PROTOCOLS`` (address ``HOST:PORT``, ``[IPv6]:PORT`` too; the port 1..65535, or 0 to
    listen on any free one) or ``PATH_PROTOCOLS`` (address a path).  Whether the host is
    reachable is not checked: a client or peer retries an endpoint that is not up yet."""
    def refuse(problem):
        raise EndpointError(flag, endpoint, problem)

    text = str(endpoint)
    protocol, slash, rest = text.partition("/")
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    if not slash or not protocol or not address:
        refuse(f"Endpoints must be of the form PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:{ZENOH_PORT}")
    if protocol in PATH_PROTOCOLS:
        return text
    if protocol not in IP_PROTOCOLS:
        refuse(f"unknown protocol {protocol!r} (known: {', '.join(IP_PROTOCOLS + PATH_PROTOCOLS)})")
    host, colon, port = address.rpartition(":")
    if not colon or not host:
        refuse(f"expected {protocol}/HOST:PORT, e.g. {protocol}/127.0.0.1:{ZENOH_PORT}")
    if not _HOST.fullmatch(host):
        refuse(f"{host!r} is not a host name or address (an IPv6 address goes in brackets: [::1])")
    lowest = 0 if listen else 1
    if not port.isdigit() or not lowest <= int(port) <= 65535:
        refuse(f"port {port!r} is not in {lowest}..65535" + (" (0: any free port)" if listen else ""))
    return text


@dataclass(frozen=True)
class ZenohOptions:
    mode: str = "peer"
    connect: tuple = ()
    listen: tuple = ("tcp/127.0.0.1:0",)
    cfg: tuple = ()  # (key, json5 value) pairs

    def config(self) -> zenoh.Config:
        """The Zenoh configuration.  An endpoint that cannot be one raises EndpointError
        (``check_endpoint``), a value Zenoh refuses ValueError; both name the flag."""
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        for flag, key, values in (("--listen", "listen/endpoints", self.listen),
                                  ("--connect", "connect/endpoints", self.connect)):
            for value in values:  # one at a time: the error names the endpoint at fault
                check_endpoint(value, flag, listen=flag == "--listen")
                _insert(conf, key, json.dumps([value]), f"{flag} {value}")
            if values:
                _insert(conf, key, json.dumps(list(values)), flag)
        for key, value in self.cfg:
            _insert(conf, key, value, f"--cfg {key}:{value}")
        return conf

    def to_args(self) -> list[str]:
        """The same options as command-line flags (for spawning a service)."""
        out = ["--mode", self.mode]
        for e in self.connect:
            out += ["--connect", e]
        for e in self.listen:
            out += ["--listen", e]
        for k, v in self.cfg:
            out += ["--cfg", f"{k}:{v}"]
        return out


def zenoh_reason(exc: Exception) -> str:
    """Zenoh's own words from one of its errors, without the Rust source locations."""
    text = str(exc)
    m = re.search(r'msg: "(.*?)(?: at /[^"]*)?"', text)
    if m:
        text = m.group(1)
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", text).strip()
    text = re.sub(r'^Str\("(.*)"\)$', r"\1", text)
    # a JSON5 parser's error drawn over lines (escaped in Zenoh's message): its verdict and where
    drawn = re.search(r"-->\s*(\d+:\d+).*\\n\s*=\s*(.*)$", text)
    return f"{drawn.group(2)} (at line:column {drawn.group(1)} of the value)" if drawn else text


def _insert(conf: zenoh.Config, key: str, value: str, flag: str) -> None:
    try:
        conf.insert_json5(key, value)
    except zenoh.ZError as exc:
        raise ValueError(f"{flag}: {zenoh_reason(exc)}") from None


def open_session(options: ZenohOptions) -> zenoh.Session:
    return zenoh.open(options.config())
