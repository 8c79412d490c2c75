"""What the runner drives, whichever transport carries the nodes: the ``Cell`` protocol, and
the two ways to open one.  The choice between them is made here, once
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
from pathlib import Path
from typing import Callable, Protocol

from services.runtime.cycle import CLOCKS


class ServiceLost(RuntimeError):
    """A service of the run disappeared.  ``summary``: the robot's summary of the
    episode it then stopped (None if there was no episode, or the robot is the one lost)."""

    def __init__(self, role: str, message: str, summary: dict | None = None):
        super().__init__(message)
        self.role = role
        self.summary = summary


class Cell(Protocol):
    """The nodes of one run as the runner sees them."""

    restarts: list  # services started again by their restart policy: role, lost_at_s, exit_code, back_after_s

    def start(self) -> None:
        """Bring the services up and wait until each is ready."""

    def where(self) -> list[dict]:
        """Where each service ran, when the run was split across hosts: name, address,
        namespace, roles."""

    def request(self, role: str, cmd: str, timeout: float = 30.0, **args) -> dict:
        """A control request, answered by the role's node; RuntimeError('<role> refused ...')
        on a refusal, ``ServiceLost`` when the role is gone."""

    def publish(self, topic: str, payload: bytes) -> None:
        """A message of the runner's own (``runner/event``)."""

    def run_episode(self, answers_from, stop_on, max_seconds: float, progress=None, listening=()) -> dict:
        """One episode of FRI cycles (the robot's 'run'), driven to its end: its summary.
        ``listening``: the tokens the robot waits for before the first cycle (what the
        resets of roles that subscribe on demand replied; services.transport.process)."""

    def stop_episode(self, timeout: float = 30.0) -> dict | None:
        """End the episode in progress now (``run_episode`` was interrupted): the robot
        closes its open cycle and sends its summary, returned here (None if none came)."""

    def unresponsive(self, roles) -> list[str]:
        """The roles among ``roles`` that are alive but do not answer (lost from now on)."""

    def statistics(self, roles) -> dict:
        """What each service says of itself (links, counters), before they stop."""

    def post_mortem(self) -> list[str]:
        """What the services that died left in their logs."""

    def kill(self) -> int:
        """Kill every service process now (a second Ctrl-C); how many there were."""

    def stop(self, roles, before_report: bool) -> dict:
        """Before the report: stop the services (their exit codes); after it: let go of
        everything else (sessions, hosts)."""


@dataclass(frozen=True)
class Start:
    """What starting a run's services needs beyond their node configs."""

    clock: str
    log_dir: Path
    # per role: (SCHED_FIFO priority or None, CPUs or ()) from the realtime profile
    placement: Callable[[str], tuple]
    ready_timeout: float = 60.0
    restartable: frozenset = frozenset()  # roles started again when lost (scenario 'restart:')
    on_restart: Callable[[str], None] | None = None


@dataclass(frozen=True)
class InProcess:
    """Every node in this process, lockstep."""

    name = "inproc"
    clocks = ("lockstep",)
    offloads_recording = True  # MCAP writing in a helper process: it took a fifth of each cycle here
    spawns = False

    def open(self, run_id: str, configs: dict, start: Start) -> Cell:
        from services.transport.inproc import InProcessCell

        return InProcessCell(run_id, configs)

    def describe(self) -> str:
        return "in-process"


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
            attach: bool = False):
    """The transport called ``transport`` with its options, checked before anything starts:
    a hosts layout against the run's ``roles`` (HostsError), every credential (CredentialsError
    naming the file)."""
    if transport == "inproc":
        return InProcess()
    if transport != "zenoh":
        raise ValueError(f"transport must be one of {', '.join(TRANSPORTS)}, got {transport!r}")
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
