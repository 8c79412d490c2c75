"""The flags every Zenoh program shares (``--mode``, ``--connect``, ``--listen``, ``--cfg``,
``--sched-fifo``, ``--cpus``), defined once, as zenoh-python's examples do.

The environment variable ``ETAR_ZENOH_CONNECT`` (comma-separated) is the default
for ``--connect``, ``ETAR_ZENOH_MODE`` for ``--mode``.
"""

from __future__ import annotations

import argparse
import os

from services.transport.session import ZenohOptions


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


