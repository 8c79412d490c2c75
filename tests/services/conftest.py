import signal
import time
from contextlib import contextmanager

import pytest

from services.transport.launch import free_port
from services.transport.service import Service
from services.transport.session import ZenohOptions, open_session


@contextmanager
def service_with_peer(name: str, run_prefix: str):
    """A Service called ``name`` listening on a free loopback port, its run id, and a
    second Zenoh session connected to it; closed afterwards, with the signal handlers
    the Service installed put back."""
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run_id = f"{run_prefix}-{int(time.time() * 1000)}"
    svc = Service(name, run_id, ZenohOptions(listen=(endpoint,)))
    svc.__enter__()
    peer = open_session(ZenohOptions(connect=(endpoint,)))
    try:
        yield svc, run_id, peer
    finally:
        peer.close()
        svc.__exit__(None, None, None)
        for sig, h in handlers.items():
            signal.signal(sig, h)


@pytest.fixture(scope="session")
def foxglove_run_dir(tmp_path_factory):
    """A demonstration and a reproduction of the smoke task, in one process: what the
    Foxglove tests (the visual topics, the viewer) look at, made once per session."""
    from tests import support

    out = tmp_path_factory.mktemp("foxglove")
    scenario = support.scenario("smoke", {"demonstrate.count": 1, "learn.phases": 2})
    report = support.run(scenario, out / "run", transport="inproc", run_id="foxglove")
    assert report["error"] is None, report["error"]
    return out / "run"
