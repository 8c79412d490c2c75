"""Starting, watching and stopping service processes (what the runner and the tests use).

Each service runs as ``python -m services.cli.roles ROLE`` in its own process group,
with its output in a log file.  Readiness is its liveliness token, never a
sleep.  Once ready, the runner watches every token: the moment one disappears
(the process died, or its session did) that service is *lost*, an episode in
progress is stopped by the robot (its summary kept) and ``ServiceLost`` names
the service and when; a request to a lost service fails at once instead of
waiting for its timeout.  Stopping escalates SIGINT -> SIGTERM -> SIGKILL, each
with a timeout.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

from robot_sim.fri import FRI_CYCLE_NS
from services.runtime import topics
from services.runtime.config import config_to_args
from services.transport.cell import ServiceLost, Start
from services.transport.service import alive_services

# every service process runs this module with its role as the first argument
PROGRAM_MODULE = "services.cli.roles"


MAX_RESTARTS = 3  # per role and run: a service that keeps dying is lost


_HANDED_OUT: set[int] = set()
_HANDED_OUT_LOCK = threading.Lock()


def free_port() -> int:
    """A loopback port free now and not handed out before by this process: two runs
    started at once in one process were both given the same one by the kernel."""
    with _HANDED_OUT_LOCK:
        while True:
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                port = s.getsockname()[1]
            if port not in _HANDED_OUT:
                _HANDED_OUT.add(port)
                return port


@dataclass
class ServiceProcess:
    name: str
    popen: subprocess.Popen
    log_path: Path

    def alive(self) -> bool:
        return self.popen.poll() is None

    def tail(self, n: int = 30) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""


def spawn(name: str, args: list[str], log_dir: Path, env: dict | None = None, prefix=()) -> ServiceProcess:
    """``prefix``: what runs the process elsewhere (``ip netns exec NS``: on a host of
    services.transport.hosts; it execs the service, so the pid is still the service's)."""
    log_dir.mkdir(parents=True, exist_ok=True)
    log_path = log_dir / f"{name}.log"
    log = open(log_path, "ab")
    popen = subprocess.Popen([*prefix, sys.executable, "-m", PROGRAM_MODULE, name, *args], stdout=log, stderr=subprocess.STDOUT,
                             stdin=subprocess.DEVNULL, start_new_session=True, env=env)
    log.close()
    return ServiceProcess(name, popen, log_path)


def wait_alive(session, run_id: str, names, processes, timeout: float = 60.0) -> None:
    """Until every named service's liveliness token is seen; raise naming the
    ones missing (with the end of their logs) if one dies or time runs out."""
    deadline = time.monotonic() + timeout
    missing = set(names)
    while missing:
        missing -= alive_services(session, run_id, timeout=0.5)
        if not missing:
            return
        for p in processes:
            if p.name in missing and not p.alive():
                raise RuntimeError(f"service {p.name} exited with {p.popen.returncode} before it was ready:\n"
                                   f"{p.tail()}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"services not ready after {timeout} s: {sorted(missing)}")
        time.sleep(0.1)


def stop(processes, timeouts=(5.0, 3.0, 2.0), grace: float = 5.0) -> dict:
    """Give processes ``grace`` seconds to exit by themselves (after a shutdown
    request), then SIGINT, SIGTERM and SIGKILL to each process group; returns
    the exit codes (negative: killed by that signal)."""
    _wait_all(processes, grace)
    codes = {}
    for sig, timeout in zip((signal.SIGINT, signal.SIGTERM, signal.SIGKILL), timeouts):
        running = [p for p in processes if p.alive()]
        if not running:
            break
        for p in running:
            try:
                os.killpg(p.popen.pid, sig)
            except ProcessLookupError:
                pass
        _wait_all(running, timeout)
    for p in processes:
        codes[p.name] = p.popen.poll()
    return codes


def _wait_all(processes, seconds: float) -> None:
    """Wait until every process has exited or ``seconds`` have passed, whichever is first."""
    deadline = time.monotonic() + seconds
    for p in processes:
        try:
            p.popen.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass


class ServiceProcesses:
    """The runner's side of a run over Zenoh: one process per role (or, with
    ``attach``, services somebody else started), control requests as Zenoh queries,
    an episode as the robot's 'run' request and its ``robot/episode`` summary."""

    def __init__(self, run_id: str, start: Start, configs: dict, *, attach: bool = False, zenoh=None, tls=None,
                 hosts=None):
        """``configs``: each role's node config; ``tls``: the run's credentials
        (services.transport.credentials); ``hosts``: the services on hosts in network
        namespaces (services.transport.hosts), already up.  With either, the runner's
        session is the run's router and every service is its client."""
        from services.transport.session import ZenohOptions, open_session

        self.run_id = run_id
        self.log_dir = Path(start.log_dir)
        self.attach = attach
        self.hosts = hosts
        self.tls = tls
        self.user_zenoh = zenoh
        self._start = start
        self._configs = dict(configs)
        address = "127.0.0.1"
        hosts_cfg = ()
        if hosts is not None:
            from services.transport.hosts import ROUTER_ADDRESS, ZENOH_CFG

            address, hosts_cfg = ROUTER_ADDRESS, ZENOH_CFG
        if zenoh is not None:
            self.zenoh, self.endpoint = zenoh, ""
        elif tls is not None:
            from services.transport.credentials import router_options

            self.endpoint = f"tls/{address}:{free_port()}"
            options = router_options(tls, run_id, self.endpoint)
            self.zenoh = replace(options, cfg=options.cfg + hosts_cfg)
        elif hosts is not None:
            self.endpoint = f"tcp/{address}:{free_port()}"
            self.zenoh = ZenohOptions(mode="router", connect=(), listen=(self.endpoint,), cfg=hosts_cfg)
        else:
            self.endpoint = f"tcp/127.0.0.1:{free_port()}"
            self.zenoh = ZenohOptions(listen=(self.endpoint,))
        self.session = open_session(self.zenoh)
        self.processes: list[ServiceProcess] = []
        self._publishers = {}
        # robot/episode summaries by the first cycle of their episode: the runner takes the
        # one of the episode it started, never a duplicate or a stale one (a foreign peer's
        # copy of an earlier summary once ended a demonstration after 1.5 s)
        self._summaries: dict[int, dict] = {}
        self._episode_first = None
        self._sub = self.session.declare_subscriber(topics.key(run_id, "robot/episode"), self._on_episode)
        self._stopped = False
        self._codes = {}
        self._wake = threading.Event()  # an episode's summary came, or a service was lost
        self.watched: set = set()  # the roles of this run, once ready
        self.lost: dict = {}  # role -> monotonic time its token disappeared
        self._t0 = time.monotonic()
        self._alive_sub = None
        # restart policies (scenario 'restart:'): the roles started again when lost, at most
        # MAX_RESTARTS times each; on_restart(role) re-synchronises one that is back
        self.restartable: set = set(start.restartable)
        self.on_restart = start.on_restart
        self.restarts: list = []
        self._args: dict = {}

    def start(self) -> None:
        """Spawn each role's process (none with ``attach``) and wait until every one is alive."""
        roles = list(self._configs)
        if not self.attach:
            for role in roles:
                self._args[role] = self.service_args(role)
                self.processes.append(self._spawn(role))
        wait_alive(self.session, self.run_id, roles, self.processes, timeout=self._start.ready_timeout)
        self.watch(roles)

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
            from services.transport.credentials import client_options
            from services.transport.hosts import ZENOH_CFG
            from services.transport.session import ZenohOptions

            zo = (client_options(self.tls, role, self.endpoint) if self.tls is not None
                  else ZenohOptions(mode="client", connect=(self.endpoint,), listen=()))
            if self.hosts is not None:
                zo = replace(zo, cfg=zo.cfg + ZENOH_CFG)
            args += zo.to_args()
        else:
            args += ["--connect", self.endpoint]
        return args + config_to_args(self._configs[role])

    def where(self) -> list[dict]:
        """The hosts the services ran on, when the run was split across hosts."""
        if self.hosts is None:
            return []
        return [{"name": h.name, "address": h.address, "namespace": h.namespace, "roles": list(h.roles)}
                for h in self.hosts.hosts]

    def kill(self) -> int:
        """Every service process killed now (SIGKILL to its group)."""
        for p in self.processes:
            try:
                os.killpg(p.popen.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        return len(self.processes)

    def _spawn(self, role: str) -> ServiceProcess:
        prefix = self.hosts.command_prefix(role) if self.hosts is not None else ()
        return spawn(role, self._args[role], self.log_dir, prefix=prefix)

    def restart(self, role: str, timeout: float = 60.0) -> dict:
        """Start a lost role's process again (its restart policy) and wait until it is alive;
        then ``on_restart(role)`` re-synchronises it.  What happened goes in ``restarts``."""
        lost_at = self.lost[role]
        i = next(i for i, p in enumerate(self.processes) if p.name == role)
        old = self.processes[i]
        if old.alive():  # hung or cut off: it must not come back beside its successor
            try:
                os.killpg(old.popen.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            old.popen.wait(10)
        self.processes[i] = self._spawn(role)
        wait_alive(self.session, self.run_id, [role], [self.processes[i]], timeout=timeout)
        del self.lost[role]
        record = {"role": role, "lost_at_s": round(lost_at - self._t0, 3), "exit_code": old.popen.returncode,
                  "back_after_s": round(time.monotonic() - lost_at, 3)}
        self.restarts.append(record)
        if self.on_restart is not None:
            self.on_restart(role)
        return record

    def _may_restart(self, role: str) -> bool:
        return (role in self.restartable and not self.attach
                and sum(r["role"] == role for r in self.restarts) < MAX_RESTARTS)

    def _restart_lost(self) -> None:
        """Every lost role with a restart policy left is started again (one lost while
        another was being restarted too)."""
        while waiting := [r for r in self.lost if self._may_restart(r)]:
            self.restart(min(waiting, key=self.lost.get))

    def watch(self, roles) -> None:
        """From now on, a role whose liveliness token disappears is lost."""
        import zenoh

        self.watched = set(roles)
        self._t0 = time.monotonic()

        def on_token(sample) -> None:
            role = str(sample.key_expr).rsplit("/", 1)[-1]
            if role in self.watched and sample.kind == zenoh.SampleKind.DELETE and role not in self.lost:
                self.lost[role] = time.monotonic()
                self._wake.set()

        self._alive_sub = self.session.liveliness().declare_subscriber(topics.alive(self.run_id, "*"), on_token)
        # a token that went away between wait_alive and the subscriber is missing now
        missing = self.watched - alive_services(self.session, self.run_id, timeout=1.0)
        for role in missing:
            self.lost.setdefault(role, time.monotonic())

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
                self.lost[role] = time.monotonic()
        return silent

    def lost_message(self, role: str, during: str = "") -> str:
        at = self.lost[role] - self._t0
        proc = next((p for p in self.processes if p.name == role), None)
        code = proc.popen.poll() if proc is not None else None
        how = f"its process exited with {code}" if code is not None else "its liveliness token disappeared"
        host = self.hosts.host_of(role) if self.hosts is not None else None
        where = f" on {host.describe()}" if host is not None else ""
        return f"service {role}{where} lost {at:.1f} s into the run{during}: {how}"

    def _on_episode(self, sample) -> None:
        from services.runtime.messages import EPISODE_SUMMARY

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
        from services.transport.service import request

        if role in self.lost and self._may_restart(role):
            self.restart(role)
        if role in self.lost:
            raise ServiceLost(role, self.lost_message(role) + f"; '{cmd}' not sent")
        return request(self.session, self.run_id, role, cmd, timeout=timeout, **args)

    def run_episode(self, answers_from, stop_on, max_seconds, progress=None) -> dict:
        """One episode (the robot's 'run'); its summary from ``robot/episode``.
        ``progress(simulated seconds)``, when given, is called about once a second
        from the robot's status (which it serves every 100 cycles during an episode)."""
        self._wake.clear()
        self._summaries.clear()
        first = self.request("robot", "run", wait_for=list(answers_from), stop_on=stop_on,
                             max_seconds=max_seconds)["seq"]
        self._episode_first = int(first)
        started = time.monotonic()
        # lockstep runs at the pace of the slowest participant: allow a generous wall-clock budget
        deadline = started + max(120.0, 30.0 * max_seconds)
        while (summary := self._episode_summary()) is None:
            if self.lost:
                self._restart_lost()  # a role with a restart policy is back, and the episode goes on
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
        raise ServiceLost(role, self.lost_message(role, during), summary)

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

    def post_mortem(self) -> list[str]:
        return [f"--- {p.name} exited with {p.popen.returncode}; end of its log:\n{p.tail()}"
                for p in self.processes if not p.alive()]

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
                # a lost service that is still there is hung or stopped: it cannot shut down
                for p in self.processes:
                    if p.name in self.lost and p.alive():
                        try:
                            os.killpg(p.popen.pid, signal.SIGKILL)
                        except ProcessLookupError:
                            pass
                self._shutdown(roles)
                self._codes = stop(self.processes)
            return self._codes
        if self._stopped:
            return self._codes
        self._stopped = True
        try:
            if self.attach:
                self._shutdown(roles)
            if self._alive_sub is not None:
                self._alive_sub.undeclare()
            self._sub.undeclare()
            self.session.close()
        finally:
            if self.hosts is not None:
                self.hosts.down()
        return self._codes
