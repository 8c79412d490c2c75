"""``etar-bench router``: a real Zenoh router that stops cleanly on Ctrl-C and on SIGTERM
(what `docker-compose down` sends it, as process 1 of its container)."""

import signal
import subprocess
import sys
import time

import pytest

from services.transport.launch import free_port
from tests.support import popen_as_from_a_terminal


@pytest.mark.zenoh
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "Ctrl-C"])
def test_the_router_stops_at_once_on_sigterm_and_ctrl_c(sig):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    # SIGINT at its default in the router, whatever the shell that started the tests ignores
    proc = popen_as_from_a_terminal([sys.executable, "-m", "services.cli.bench", "router", "--listen", endpoint],
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stderr.readline()  # what the command lines say goes to stderr
        assert f"zenoh router listening on {endpoint}" in first, (first, proc.stderr.read() if proc.poll() else "")
        t0 = time.monotonic()
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=10)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "zenoh router stopped" in err and "Traceback" not in err, (out, err)
    assert took < 3.0, f"the router took {took:.1f} s to stop"


@pytest.mark.zenoh
def test_a_router_told_port_0_says_the_port_it_listens_on_and_a_peer_connects_there():
    """--listen PROTO/HOST:0 lets the system choose the port: the first line names the port
    chosen for each endpoint, TCP and UDP, two port 0s two ports (it said ':0', which nobody
    can connect to; then UDP's stayed ':0' and two TCP ones both named every port), and a
    client session connects to each: on three addresses, each its own port (Zenoh lists its
    locators in an order of its own, not the order they were given in)."""
    import re

    import zenoh

    proc = subprocess.Popen([sys.executable, "-m", "services.cli.bench", "router", "--listen", "tcp/127.0.0.3:0",
                             "--listen", "tcp/127.0.0.1:0", "--listen", "udp/127.0.0.1:0", "--listen", "tcp/127.0.0.2:0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stderr.readline()
        m = re.search(r"listening on tcp/127\.0\.0\.3:(\d+), tcp/127\.0\.0\.1:(\d+), udp/127\.0\.0\.1:(\d+), "
                      r"tcp/127\.0\.0\.2:(\d+);", first)
        assert m and all(int(p) > 0 for p in m.groups()) and len({m[1], m[2], m[4]}) == 3, first
        for endpoint in (f"tcp/127.0.0.3:{m[1]}", f"tcp/127.0.0.1:{m[2]}", f"udp/127.0.0.1:{m[3]}",
                         f"tcp/127.0.0.2:{m[4]}"):
            conf = zenoh.Config()
            conf.insert_json5("mode", '"client"')
            conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
            with zenoh.open(conf) as session:
                assert str(session.info.routers_zid()[0]), endpoint  # joined that router
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=10)
