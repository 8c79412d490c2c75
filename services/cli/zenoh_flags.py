"""The flags every Zenoh program shares (``--mode``, ``--connect``, ``--listen``, ``--cfg``,
``--sched-fifo``, ``--cpus``), defined once, as zenoh-python's examples do.

The environment variable ``ETAR_ZENOH_CONNECT`` (comma-separated) is the default
for ``--connect``, ``ETAR_ZENOH_MODE`` for ``--mode``.  The endpoints are checked
where the session's configuration is made (``services.transport.session.check_endpoint``),
so a router that builds its ``ZenohOptions`` itself refuses the same endpoints.
"""

from __future__ import annotations

import argparse
import os

from services.transport.session import ZENOH_PORT, EndpointError, ZenohOptions, check_endpoint

FIFO_PRIORITIES = range(1, 100)  # Linux's SCHED_FIFO priorities (99 the highest)
FIFO_DEFAULT = 50  # --sched-fifo without a priority


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, process_flags: bool = True, run: bool = False) -> None:
    """The Zenoh flags, and with ``process_flags`` the process's own (``--sched-fifo PRIORITY``,
    ``--cpus``) unless ``parser`` already has a ``sched_fifo`` of its own.  ``run``: the
    runner's, which it gives its services too, only with ``--connect`` (see ``etar-bench run``)."""
    g = parser.add_argument_group("zenoh")
    # the runner hands these to every service it starts, so alone (without a session to join) they link nothing
    needs = "; with --connect only (and --transport zenoh)" if run else ""
    # None when not given: the environment's is a default, and the runner tells the two apart
    g.add_argument("--mode", choices=("peer", "client", "router"), default=None,
                   help=f"Zenoh session mode (default peer, or $ETAR_ZENOH_MODE){needs}")
    g.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to connect to, PROTOCOL/HOST:PORT with a port in 1..65535, e.g. "
                        f"tcp/127.0.0.1:{ZENOH_PORT} (repeatable; " + (
                            "the runner and every service it starts join the session there with these flags; "
                            "default: none, the runner makes its own on loopback; --transport zenoh only)" if run else
                            "default $ETAR_ZENOH_CONNECT, comma-separated; an endpoint not up yet is retried)"))
    g.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on, PROTOCOL/HOST:PORT with a port in 0..65535 (0: any free one) "
                        f"(repeatable; default tcp/127.0.0.1:0 for peers, none for clients){needs}")
    g.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                   help="any Zenoh configuration key with a JSON5 value, e.g. transport/unicast/lowlatency:true "
                        f"(repeatable; default none){needs}")
    if process_flags and not any(a.dest == "sched_fifo" for a in parser._actions):
        add_sched_fifo_argument(parser)


def add_sched_fifo_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sched-fifo", nargs="?", type=fifo_priority, const=FIFO_DEFAULT, default=0,
                        metavar="PRIORITY",
                        help=f"run the whole process (its Zenoh threads too) under SCHED_FIFO at PRIORITY, "
                             f"{FIFO_PRIORITIES[0]}..{FIFO_PRIORITIES[-1]} ({FIFO_PRIORITIES[-1]} the highest; "
                             f"without a value {FIFO_DEFAULT}), if permitted; 0: off (default 0). The ready line "
                             "says whether it was granted, and why not")
    parser.add_argument("--cpus", type=cpu_list, default=(), metavar="LIST",
                        help="pin the whole process to these CPUs, e.g. 1 or 0,2-3 (default: any)")


def fifo_priority(text: str) -> int:
    """A ``--sched-fifo`` value: a SCHED_FIFO priority, or 0 for none."""
    try:
        priority = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--sched-fifo {text}: expected a priority, an integer in "
                                         f"{FIFO_PRIORITIES[0]}..{FIFO_PRIORITIES[-1]} (0: off)") from None
    if priority != 0 and priority not in FIFO_PRIORITIES:
        raise argparse.ArgumentTypeError(f"--sched-fifo {text}: a SCHED_FIFO priority is "
                                         f"{FIFO_PRIORITIES[0]}..{FIFO_PRIORITIES[-1]} (0: off)")
    return priority


def cpu_list(text: str) -> tuple:
    cpus = set()
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        try:
            cpus.update(range(int(lo), int(hi or lo) + 1))
        except ValueError:
            raise argparse.ArgumentTypeError(f"--cpus {text}: expected CPUs like 1 or 0,2-3") from None
    usable = os.sched_getaffinity(0)
    if not cpus or not cpus <= usable:
        raise argparse.ArgumentTypeError(f"--cpus {text}: this process may use CPUs "
                                         f"{','.join(map(str, sorted(usable)))}")
    return tuple(sorted(cpus))


def zenoh_options(args: argparse.Namespace) -> ZenohOptions:
    """The session options of the parsed flags; ValueError naming the flag and the value
    (``EndpointError`` for an endpoint) if one cannot work."""
    mode = args.mode or os.environ.get("ETAR_ZENOH_MODE", "peer")
    connect = args.connect
    if connect is None:
        env = os.environ.get("ETAR_ZENOH_CONNECT", "")
        connect = [check_endpoint(e.strip(), "$ETAR_ZENOH_CONNECT") for e in env.split(",") if e.strip()]
    listen = args.listen
    if listen is None:
        listen = [] if mode == "client" else ["tcp/127.0.0.1:0"]
    cfg = []
    for item in args.cfg:
        k, colon, v = item.partition(":")
        if not colon or not k:
            raise ValueError(f"--cfg {item}: expected KEY:VALUE, e.g. transport/unicast/lowlatency:true")
        cfg.append((k, v))
    options = ZenohOptions(mode, tuple(connect), tuple(listen), tuple(cfg))
    options.config()  # a value Zenoh refuses is named now, not as a traceback when the session opens
    return options


__all__ = ["EndpointError", "add_sched_fifo_argument", "add_zenoh_arguments",
           "check_endpoint", "cpu_list", "fifo_priority", "zenoh_options"]
