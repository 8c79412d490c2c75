"""Zenoh session configuration shared by every service (one helper, as zenoh-python's examples do).

Embedded default: a peer on loopback, multicast scouting off, listening on its
own ``tcp/127.0.0.1:0`` and connecting to the endpoints given (the runner's):
Zenoh peers do not relay for one another, so every peer listens and gossip
links them directly (DESIGN.md).  ``--mode client --connect tcp/HOST:PORT``
joins a Zenoh router instead (docker-compose).  ``--cfg KEY:VALUE`` sets any
other Zenoh configuration key (a misspelt key is refused by Zenoh).
The environment variable ``ETAR_ZENOH_CONNECT`` (comma-separated) is the default
for ``--connect``, ``ETAR_ZENOH_MODE`` for ``--mode``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
from dataclasses import dataclass

import zenoh


@dataclass(frozen=True)
class ZenohOptions:
    mode: str = "peer"
    connect: tuple = ()
    listen: tuple = ("tcp/127.0.0.1:0",)
    cfg: tuple = ()  # (key, json5 value) pairs

    def config(self) -> zenoh.Config:
        """The Zenoh configuration; a value Zenoh refuses raises ValueError naming the flag."""
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        for flag, key, values in (("--listen", "listen/endpoints", self.listen),
                                  ("--connect", "connect/endpoints", self.connect)):
            for value in values:  # one at a time: the error names the endpoint at fault
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


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("zenoh")
    g.add_argument("--mode", choices=("peer", "client", "router"),
                   default=os.environ.get("ETAR_ZENOH_MODE", "peer"), help="Zenoh session mode (default peer)")
    g.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; default $ETAR_ZENOH_CONNECT)")
    g.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable; default tcp/127.0.0.1:0 for peers, none for clients)")
    g.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                   help="any Zenoh configuration key with a JSON5 value, e.g. transport/unicast/lowlatency:true")
    if not any(a.dest == "sched_fifo" for a in parser._actions):
        add_sched_fifo_argument(parser)


def add_sched_fifo_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sched-fifo", nargs="?", type=int, const=50, default=0, metavar="PRIORITY",
                        help="run the whole process (its Zenoh threads too) under SCHED_FIFO at PRIORITY "
                             "(default 50) if permitted; the report says whether it was used")
    parser.add_argument("--cpus", type=cpu_list, default=(), metavar="LIST",
                        help="pin the whole process to these CPUs, e.g. 1 or 0,2-3 (default: any)")


def cpu_list(text: str) -> tuple:
    cpus = set()
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        try:
            cpus.update(range(int(lo), int(hi or lo) + 1))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected CPUs like 1 or 0,2-3, got {text!r}") from None
    usable = os.sched_getaffinity(0)
    if not cpus or not cpus <= usable:
        raise argparse.ArgumentTypeError(f"CPUs {text!r}: this process may use CPUs "
                                         f"{','.join(map(str, sorted(usable)))}")
    return tuple(sorted(cpus))


def zenoh_reason(exc: Exception) -> str:
    """Zenoh's own words from one of its errors, without the Rust source locations."""
    text = str(exc)
    m = re.search(r'msg: "(.*?)(?: at /[^"]*)?"', text)
    if m:
        text = m.group(1)
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", text).strip()
    return re.sub(r'^Str\("(.*)"\)$', r"\1", text)


def _insert(conf: zenoh.Config, key: str, value: str, flag: str) -> None:
    try:
        conf.insert_json5(key, value)
    except zenoh.ZError as exc:
        raise ValueError(f"{flag}: {zenoh_reason(exc)}") from None


def zenoh_options(args: argparse.Namespace) -> ZenohOptions:
    connect = args.connect
    if connect is None:
        env = os.environ.get("ETAR_ZENOH_CONNECT", "")
        connect = [e for e in env.split(",") if e]
    listen = args.listen
    if listen is None:
        listen = [] if args.mode == "client" else ["tcp/127.0.0.1:0"]
    cfg = []
    for item in args.cfg:
        if ":" not in item:
            raise SystemExit(f"--cfg expects KEY:VALUE, got {item!r}")
        k, v = item.split(":", 1)
        cfg.append((k, v))
    options = ZenohOptions(args.mode, tuple(connect), tuple(listen), tuple(cfg))
    options.config()  # a value Zenoh refuses is named now, not as a traceback when the session opens
    return options


def open_session(options: ZenohOptions) -> zenoh.Session:
    return zenoh.open(options.config())
