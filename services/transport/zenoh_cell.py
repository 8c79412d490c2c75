"""The runner's ``Cell`` over Zenoh: one process per role (``services.transport.launch``
supervises them), control requests as Zenoh queries, an episode as the robot's 'run'
request and its ``robot/episode`` summary.  With ``tls`` or ``hosts`` the runner's session
is the run's router and every service its client; otherwise the services are peers that
connect to the runner's loopback endpoint (or to the session ``zenoh`` names)."""

from __future__ import annotations

import threading
import time
from dataclasses import replace

from robot_sim.cycle import FRI_CYCLE_NS
from services.runtime import topics
from services.runtime.config import config_to_args
from services.runtime.messages import EPISODE_SUMMARY
from services.transport.cell import ServiceLost, Start
from services.transport.credentials import client_options, router_options
from services.transport.hosts import ROUTER_ADDRESS, ZENOH_CFG as HOSTS_CFG
from services.transport.launch import Supervisor, free_port
from services.transport.service import request
from services.transport.session import ZenohOptions, open_session


class ZenohCell:
    """The nodes of one run, each in its own process (a ``services.transport.cell.Cell``)."""

    def __init__(self, run_id: str, start: Start, configs: dict, *, attach: bool = False, zenoh=None, tls=None,
                 hosts=None):
        """``configs``: each role's node config; ``tls``: the run's credentials
        (services.transport.credentials); ``hosts``: the services on hosts in network
        namespaces (services.transport.hosts), already up.  With either, the runner's
        session is the run's router and every service is its client."""
        self.run_id = run_id
        self.attach = attach
        self.hosts = hosts
        self.tls = tls
        self.user_zenoh = zenoh
        self._start = start
        self._configs = dict(configs)
        address = "127.0.0.1"
        hosts_cfg = ()
        if hosts is not None:
            address, hosts_cfg = ROUTER_ADDRESS, HOSTS_CFG
        if zenoh is not None:
            self.zenoh, self.endpoint = zenoh, ""
            self.session = open_session(self.zenoh)
        else:
            self.session = self._listen(address, hosts_cfg)
        self._publishers = {}
        # robot/episode summaries by the first cycle of their episode: the runner takes the
        # one of the episode it started, never a duplicate or a stale one (a foreign peer's
        # copy of an earlier summary once ended a demonstration after 1.5 s)
        self._summaries: dict[int, dict] = {}
        self._episode_first = None
        self._stopped = False
        self._codes = {}
        self._wake = threading.Event()  # an episode's summary came, or a service was lost
        try:
            self._sub = self.session.declare_subscriber(topics.key(run_id, EPISODE_SUMMARY.topic), self._on_episode)
            self.supervisor = Supervisor(self.session, run_id, start.log_dir, hosts=hosts, attach=attach,
                                         restartable=start.restartable, on_restart=start.on_restart,
                                         wake=self._wake)
        except BaseException:
            self.session.close()
            raise
        self.lost = self.supervisor.lost  # role -> monotonic time it was lost

    def _listen(self, address: str, hosts_cfg: tuple):
        """The runner's session, listening on a free port it picked; a port another
        program took in between costs one more pick, not the run."""
        for attempt in range(3):
            if self.tls is not None:
                self.endpoint = f"tls/{address}:{free_port()}"
                options = router_options(self.tls, self.run_id, self.endpoint)
                self.zenoh = replace(options, cfg=options.cfg + hosts_cfg)
            elif self.hosts is not None:
                self.endpoint = f"tcp/{address}:{free_port()}"
                self.zenoh = ZenohOptions(mode="router", connect=(), listen=(self.endpoint,), cfg=hosts_cfg)
            else:
                self.endpoint = f"tcp/127.0.0.1:{free_port()}"
                self.zenoh = ZenohOptions(listen=(self.endpoint,))
            try:
                return open_session(self.zenoh)
            except Exception as e:
                if "Address already in use" not in str(e) or attempt == 2:
                    raise

    def start(self) -> None:
        """Spawn each role's process (none with ``attach``) and wait until every one is alive."""
        self.supervisor.start({role: self.service_args(role) for role in self._configs},
                              timeout=self._start.ready_timeout)

    def service_args(self, role: str) -> list[str]:
        """The command-line flags of ``role``'s process (``services.cli.roles``)."""
        priority, cpus = self._start.placement(role)
        args = ["--run-id", self.run_id, "--clock", self._start.clock]
        args += ["--sched-fifo", str(priority)] if priority else []
        args += ["--cpus", ",".join(map(str, cpus))] if cpus else []
        if self.user_zenoh is not None:
            args += self.user_zenoh.to_args()
        elif self.tls is not None or self.hosts is not None:
            # a client of the runner's router (peers listening on loopback cannot reach
            # one another across hosts), with the router's short lease on a host
            zo = (client_options(self.tls, role, self.endpoint) if self.tls is not None
                  else ZenohOptions(mode="client", connect=(self.endpoint,), listen=()))
            if self.hosts is not None:
                zo = replace(zo, cfg=zo.cfg + HOSTS_CFG)
            args += zo.to_args()
        else:
            args += ["--connect", self.endpoint]
        return args + config_to_args(self._configs[role])

    def unresponsive(self, roles, timeout: float = 1.0) -> list:
        """The roles among ``roles`` that do not answer a status request within ``timeout``
        (alive but stopped or hung); they are lost from now on."""
        silent = []
        for role in roles:
            if role in self.lost:
                continue
            try:
                self.request(role, "status", timeout=timeout)
            except (TimeoutError, RuntimeError):
                silent.append(role)
                self.supervisor.mark_lost(role)
        return silent

    def _on_episode(self, sample) -> None:
        try:
            summary = EPISODE_SUMMARY.decode(sample.payload.to_bytes())
        except ValueError:
            return
        self._summaries[summary["first_seq"]] = summary
        if summary["first_seq"] == self._episode_first:
            self._wake.set()

    def _episode_summary(self, timeout: float = 0.0) -> dict | None:
        """The summary of the episode in progress, waiting up to ``timeout`` for it."""
        deadline = time.monotonic() + timeout
        while (summary := self._summaries.get(self._episode_first)) is None and time.monotonic() < deadline:
            self._wake.wait(min(0.1, max(0.0, deadline - time.monotonic())))
            self._wake.clear()
        return summary

    def request(self, role: str, cmd: str, timeout: float = 30.0, **args) -> dict:
        if role in self.lost and self.supervisor.may_restart(role):
            self.supervisor.restart(role)
        if role in self.lost:
            raise ServiceLost(role, self.supervisor.lost_message(role) + f"; '{cmd}' not sent")
        return request(self.session, self.run_id, role, cmd, timeout=timeout, **args)

    def run_episode(self, answers_from, stop_on, max_seconds, progress=None, listening=()) -> dict:
        """One episode (the robot's 'run'); its summary from ``robot/episode``.
        ``progress(simulated seconds)``, when given, is called about once a second
        from the robot's status (which it serves every 100 cycles during an episode)."""
        self._wake.clear()
        self._summaries.clear()
        first = self.request("robot", "run", wait_for=list(answers_from), stop_on=stop_on,
                             max_seconds=max_seconds, **({"listening": list(listening)} if listening else {}))["seq"]
        self._episode_first = int(first)
        started = time.monotonic()
        # lockstep runs at the pace of the slowest participant: allow a generous wall-clock budget
        deadline = started + max(120.0, 30.0 * max_seconds)
        while (summary := self._episode_summary()) is None:
            if self.lost:
                self.supervisor.restart_lost()  # a role with a restart policy is back, and the episode goes on
            if self.lost:
                self._lost_during_episode(started)
            if time.monotonic() >= deadline:
                self.request("robot", "stop", timeout=10.0)
                summary = self._episode_summary(30.0)
                if summary is None:
                    raise TimeoutError("the robot did not end its episode")
                break
            self._wake.wait(min(1.0, max(0.0, deadline - time.monotonic())))
            self._wake.clear()
            if progress is None or self.lost or self._episode_first in self._summaries:
                continue
            try:
                seq = self.request("robot", "status", timeout=0.5).get("seq")
            except (TimeoutError, RuntimeError):
                continue  # busy: the next second will tell
            if seq is not None:
                progress(max(0, seq - first) * FRI_CYCLE_NS / 1e9)
        return summary

    def stop_episode(self, timeout: float = 30.0) -> dict | None:
        try:
            self.request("robot", "stop", timeout=min(10.0, timeout))
        except (ServiceLost, TimeoutError, RuntimeError):
            return None
        return self._episode_summary(timeout)

    def _lost_during_episode(self, started: float) -> None:
        """A service disappeared during the episode: the robot (if it is not the one lost)
        stops the episode, which closes its open cycle and holds the arm where it is,
        and its summary goes with the error."""
        role = min(self.lost, key=self.lost.get)
        during = f", {self.lost[role] - started:.1f} s into the episode"
        summary = None
        why = ""
        if "robot" not in self.lost:
            try:
                stopped = self.request("robot", "stop", timeout=10.0).get("stopped")
                summary = self._episode_summary(10.0 if stopped else 0.0)
                if summary is None:
                    why = f"; the robot {'stopped' if stopped else 'had no episode to stop'} but sent no summary"
            except (TimeoutError, RuntimeError) as exc:
                # the robot may have stopped and its answer be held up on the way: a host cut
                # off held the robot's traffic to the runner ~10 s once (not understood)
                summary = self._episode_summary(10.0)
                why = f"; the robot did not stop the episode ({type(exc).__name__}: {exc})"
        if summary is not None:
            during += f" (cycle {summary['last_seq']}, {summary['sim_seconds']:.3f} s simulated)"
        else:
            during += why
        raise ServiceLost(role, self.supervisor.lost_message(role, during), summary)

    def publish(self, topic: str, payload: bytes) -> None:
        pub = self._publishers.get(topic)
        if pub is None:
            pub = self._publishers[topic] = self.session.declare_publisher(topics.key(self.run_id, topic))
        pub.put(payload)

    def statistics(self, roles) -> dict:
        """Each service's own link statistics (receiving end), before they stop."""
        out = {}
        for role in roles:
            try:
                out[role] = self.request(role, "status", timeout=3.0)
            except Exception as exc:  # a dead service has no statistics; the report says so
                out[role] = {"error": f"{type(exc).__name__}: {exc}"}
        return out

    def _shutdown(self, roles) -> None:
        for role in roles:
            if role in self.lost:
                continue  # it cannot answer: stop's escalation ends it
            try:
                self.request(role, "shutdown", timeout=2.0)
            except Exception:  # already gone: stop's escalation handles it
                pass

    def stop(self, roles, before_report: bool) -> dict:
        """Before the report: stop the processes this runner started (exit codes).  After
        it: with ``attach``, shut the services down (containers stop with them, so only
        once the report is written), and close the session."""
        if before_report:
            if not self.attach:
                self._codes = self.supervisor.stop(lambda: self._shutdown(roles))
            return self._codes
        if self._stopped:
            return self._codes
        self._stopped = True
        try:
            if self.attach:
                self._shutdown(roles)
            self.supervisor.close()
            self._sub.undeclare()
        finally:
            try:
                self.session.close()
            finally:
                if self.hosts is not None:
                    self.hosts.down()
        return self._codes

    # what the supervisor knows, as the Cell protocol and the tests ask for it
    @property
    def processes(self) -> list:
        return self.supervisor.processes

    @property
    def restarts(self) -> list:
        return self.supervisor.restarts

    def where(self) -> list[dict]:
        return self.supervisor.where()

    def kill(self) -> int:
        return self.supervisor.kill()

    def post_mortem(self) -> list[str]:
        return self.supervisor.post_mortem()
