"""The two ways to carry a run's nodes, and the choice between them, made here once
(``carrier``): the runner asks the carrier what it can do and never compares names.

- ``InProcess``: every node in this process on an in-memory bus, lockstep only
  (``services.transport.inproc``); the recorder's MCAP writing goes to a helper
  process, since every node shares this process' CPU.
- ``OverZenoh``: one process per role over Zenoh, realtime or lockstep
  (``services.transport.zenoh_cell``): on loopback, through a router with mutual TLS,
  on hosts in network namespaces, or attached to services someone else started.
"""

from __future__ import annotations

from dataclasses import dataclass

from services.runtime.cycle import CLOCKS
from services.transport.cell import Cell, Start


ENGINES = ("per-message", "fused")
DEFAULT_ENGINE = "fused"


def check_engine(engine: str | None, in_process: bool) -> None:
    """ValueError unless ``engine`` (None: the default) is one of ENGINES, asked for in one process."""
    if engine is None:
        return
    if engine not in ENGINES:
        raise ValueError(f"--engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    if not in_process:
        raise ValueError(f"--engine {engine} steps the nodes of a run in one process: it needs --transport inproc "
                         "(over Zenoh every node is its own process)")


@dataclass(frozen=True)
class InProcess:
    """Every node in this process, lockstep.  ``engine``: how the FRI cycles are stepped,
    per-message (every message through the in-memory bus to every handler,
    ``services.transport.inproc``) or fused (the 1 kHz path walked once per cycle,
    ``services.transport.fused``); the same recordings either way."""

    engine: str = DEFAULT_ENGINE
    name = "inproc"
    clocks = ("lockstep",)
    offloads_recording = True  # MCAP writing in a helper process: it took a fifth of each cycle here
    spawns = False

    def __post_init__(self):
        check_engine(self.engine, in_process=True)

    def open(self, run_id: str, configs: dict, start: Start) -> Cell:
        if self.engine == "fused":
            from services.transport.fused import FusedCell

            return FusedCell(run_id, configs)
        from services.transport.inproc import InProcessCell

        return InProcessCell(run_id, configs)

    def describe(self) -> str:
        return f"in-process ({self.engine} engine)"


@dataclass(frozen=True)
class OverZenoh:
    """One process per role over Zenoh.  ``zenoh``: the session to join (None: the runner
    listens on a free loopback port); ``tls``: the run's credentials (the runner is the
    run's router); ``hosts``: a layout of roles on hosts in network namespaces; ``attach``:
    the services are already running (docker-compose)."""

    zenoh: object | None = None
    tls: str | None = None
    hosts: tuple | None = None  # services.transport.hosts.parse_layout's hosts
    attach: bool = False
    name = "zenoh"
    clocks = CLOCKS
    offloads_recording = False

    @property
    def spawns(self) -> bool:
        return not self.attach

    def open(self, run_id: str, configs: dict, start: Start) -> Cell:
        """The runner's session (the run's router with ``tls`` or ``hosts``), with the hosts
        up; ``start()`` then spawns the services."""
        from services.transport.hosts import Hosts
        from services.transport.zenoh_cell import ZenohCell

        hosts = Hosts(self.hosts) if self.hosts is not None else None
        if hosts is not None:
            hosts.up()
        try:
            return ZenohCell(run_id, start, configs, attach=self.attach, zenoh=self.zenoh, tls=self.tls,
                                    hosts=hosts)
        except BaseException:
            if hosts is not None:
                hosts.down()
            raise

    def describe(self) -> str:
        return "Zenoh"


TRANSPORTS = ("zenoh", "inproc")


def carrier(transport: str, roles, *, zenoh=None, tls: str | None = None, hosts: str | None = None,
            attach: bool = False, engine: str | None = None):
    """The transport called ``transport`` with its options, checked before anything starts:
    a hosts layout against the run's ``roles`` (HostsError), every credential (CredentialsError
    naming the file); ``engine`` (in one process only; None: the default)."""
    if transport == "inproc":
        return InProcess(engine or DEFAULT_ENGINE)
    if transport != "zenoh":
        raise ValueError(f"transport must be one of {', '.join(TRANSPORTS)}, got {transport!r}")
    check_engine(engine, in_process=False)
    layout = None
    if hosts is not None:
        from services.transport.hosts import parse_layout

        layout = parse_layout(hosts, roles)
    if tls is not None:
        from services.transport.credentials import client_options, router_options

        router_options(tls, "check", "tls/127.0.0.1:1")
        for role in roles:
            client_options(tls, role, "tls/127.0.0.1:1")
    return OverZenoh(zenoh=zenoh, tls=tls, hosts=layout, attach=attach)
