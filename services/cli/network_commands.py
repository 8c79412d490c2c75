"""``etar-bench`` certs and router: the network a run over several hosts needs, once the
command line is parsed (``services.cli.bench``)."""

from __future__ import annotations

import contextlib
import os
import signal
import time

from services.cli.output import say
from services.transport.session import ZENOH_PORT


def cmd_certs(args) -> int:
    from etar.parsing import empty_path
    from services.runtime.roles import CREDENTIAL_NAMES as ROLES
    from services.transport.credentials import CredentialsError, make_credentials

    try:
        empty_path(None, args.dir, "the credentials' folder")
    except ValueError as exc:
        say(f"etar-bench certs: error: {exc}")
        return 2
    try:
        out = make_credentials(args.dir, hosts=tuple(args.host or ["127.0.0.1"]), roles=ROLES + tuple(args.role))
    except CredentialsError as exc:
        say(f"etar-bench certs: error: {exc}")
        return 2
    print(f"{out}: ca.pem (ca.key signs: keep it off the hosts), router.pem/.key, and a certificate per role "
          f"({', '.join(ROLES + tuple(args.role))}); use with: etar-bench run SCENARIO --tls {out}", flush=True)
    return 0


def cmd_router(args) -> int:
    """A real Zenoh router (the Python library in router mode) for multi-host or container runs."""
    import zenoh

    from services.cli.run_commands import interrupt
    from services.transport.session import ZenohOptions, zenoh_reason

    opts = ZenohOptions(mode="router", connect=(), listen=tuple(args.listen or [f"tcp/0.0.0.0:{ZENOH_PORT}"]))
    try:
        conf = opts.config()
        session = zenoh.open(conf)
    except ValueError as exc:  # names the flag and the value
        say(f"etar-bench router: error: {exc}")
        return 2
    except zenoh.ZError as exc:  # e.g. an address it cannot listen on
        say(f"etar-bench router: error: --listen {' '.join(opts.listen)}: {zenoh_reason(exc)}")
        return 2
    # SIGTERM as Ctrl-C: in a container the router is process 1, which has no default action
    # for it, and `docker-compose down` would wait its 10 s grace and kill it
    signal.signal(signal.SIGTERM, interrupt)
    try:  # around all of it: the signal may come while the first line is being said
        with session:
            say(f"zenoh router listening on {', '.join(_ports_chosen(opts.listen))}; Ctrl-C to stop")
            while True:
                time.sleep(1.0)
    except KeyboardInterrupt:
        say("zenoh router stopped")
        return 0


def _ports_chosen(listen) -> list[str]:
    """The endpoints as the router listens on them: a TCP port 0 (the system chooses) as the
    port chosen, read from this process's listening sockets (Linux's /proc), else as given."""
    out, given = [], {e.rpartition(":")[2] for e in listen}
    for endpoint in listen:
        proto, _, address = endpoint.partition("/")
        host, _, port = address.rpartition(":")
        chosen = [p for p in _listening_tcp_ports() if str(p) not in given] \
            if port == "0" and proto in ("tcp", "tls") else []
        out.extend([f"{proto}/{host}:{p}" for p in chosen] or [endpoint])
    return out


def _listening_tcp_ports() -> list[int]:
    """The TCP ports this process listens on (none where /proc does not say)."""
    mine = set()
    try:
        for fd in os.listdir("/proc/self/fd"):
            with contextlib.suppress(OSError):  # listdir's own descriptor is closed by now
                mine.add(os.readlink(f"/proc/self/fd/{fd}"))
        ports = set()
        for table in ("/proc/self/net/tcp", "/proc/self/net/tcp6"):
            with open(table) as f:
                for row in f.read().splitlines()[1:]:
                    cols = row.split()  # local address (hex ip:port), ..., state (0A: listen), ..., inode
                    if cols[3] == "0A" and f"socket:[{cols[9]}]" in mine:
                        ports.add(int(cols[1].rsplit(":", 1)[1], 16))
        return sorted(ports)
    except OSError:
        return []
