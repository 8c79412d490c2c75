"""``etar-bench`` certs and router: the network a run over several hosts needs, once the
command line is parsed (``services.cli.bench``)."""

from __future__ import annotations

import contextlib
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
        # read-only, as zenohd's default: where a port 0 was given, the router's own locators say
        # which port the system chose
        conf.insert_json5("adminspace", '{"enabled": true, "permissions": {"read": true, "write": false}}')
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
            say(f"zenoh router listening on {', '.join(_ports_chosen(session, opts.listen))}; Ctrl-C to stop")
            while True:
                time.sleep(1.0)
    except KeyboardInterrupt:
        say("zenoh router stopped")
        return 0


def _ports_chosen(session, listen) -> list[str]:
    """The endpoints as the router listens on them: a port 0 (the system chooses) as the port
    chosen, from Zenoh's own list of the router's locators (its admin space, read-only);
    an endpoint with its port given, or when Zenoh does not say, as given."""
    import json

    locators = []
    with contextlib.suppress(Exception):  # no answer is no reason to stop a router: it says what it was given
        for reply in session.get(f"@/{session.info.zid()}/router", timeout=2.0):
            locators += json.loads(reply.ok.payload.to_bytes()).get("locators", [])
    given = {e.rpartition(":")[2] for e in listen}
    found = [(proto, host, port) for proto, _, rest in (loc.partition("/") for loc in locators)
             for host, _, port in [rest.rpartition(":")] if port not in given]
    out = list(listen)
    # a port 0 on a host takes the locator on that host; one on every address (0.0.0.0, [::])
    # or by a name Zenoh resolved (localhost) takes the first of its protocol left over
    for exact in (True, False):
        for i, endpoint in enumerate(out):
            proto, _, address = endpoint.partition("/")
            host, _, port = address.rpartition(":")
            if port != "0":
                continue
            for loc in found:
                if loc[0] == proto and (loc[1] == host or not exact):
                    # one endpoint's port is one locator per address it listens on: taken together
                    found = [f for f in found if (f[0], f[2]) != (proto, loc[2])]
                    out[i] = f"{proto}/{host}:{loc[2]}"
                    break
    return out
