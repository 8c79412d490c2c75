"""What the runner drives, whichever transport carries the nodes: the ``Cell`` protocol, what
starting one needs (``Start``) and the loss of a service (``ServiceLost``).  Which carrier
opens a cell is ``services.transport.carriers``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Protocol



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
        """Kill every service process still running now (a second Ctrl-C); how many."""

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
