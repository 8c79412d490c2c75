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
