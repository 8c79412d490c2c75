import signal
import time
from contextlib import contextmanager

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
