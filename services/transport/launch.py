"""Starting, watching and stopping the service processes of a run over Zenoh.

Each service runs as ``python -m services.cli.roles ROLE`` in its own process group,
with its output in a log file.  Readiness is its liveliness token, never a
sleep.  Once ready, ``Supervisor`` watches every token: the moment one disappears
(the process died, or its session did) that service is *lost* (the runner's cell,
``services.transport.zenoh_cell``, then stops the episode in progress and says so);
a role with a restart policy is started again.  Stopping escalates SIGINT -> SIGTERM
-> SIGKILL, each with a timeout.
"""

from __future__ import annotations

import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from services.runtime import topics
from services.transport.service import RUNNER_PID_ENV, alive_services

# every service process runs this module with its role as the first argument
PROGRAM_MODULE = "services.cli.roles"


MAX_RESTARTS = 3  # per role and run: a service that keeps dying is lost


_HANDED_OUT: set[tuple[int, int]] = set()
_HANDED_OUT_LOCK = threading.Lock()
_PICK = random.Random()  # which free port a run listens on is no part of what it records


def _ephemeral_range() -> tuple[int, int] | None:
    try:
        low, high = map(int, Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    except (OSError, ValueError):
        return None
    return low, high


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A loopback port (TCP, or UDP with ``socket.SOCK_DGRAM``) free now and not handed
    out before by this process: two runs started at once in one process were both given
    the same one by the kernel.  It is taken below the kernel's ephemeral range, where
    no outgoing connection and no bind to port 0 can be given it between now and its
    user's bind: on CI a run's router lost its port that way to the peers of a run
    started beside it ("Address already in use")."""
    ephemeral = _ephemeral_range()
    below = (max(1024, ephemeral[0] - 16384), ephemeral[0]) if ephemeral and ephemeral[0] > 2048 else None
    with _HANDED_OUT_LOCK:
        for attempt in range(1000):
            wanted = _PICK.randrange(*below) if below and attempt < 500 else 0
            with socket.socket(socket.AF_INET, kind) as s:
                try:
                    s.bind(("127.0.0.1", wanted))
                except OSError:
                    continue
                port = s.getsockname()[1]
            if (kind, port) not in _HANDED_OUT:
                _HANDED_OUT.add((kind, port))
                return port
    raise OSError("no free loopback port found in 1000 attempts")


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
    # the service stops when this process is gone (killed with -9: nothing else would tell it)
    env = dict(os.environ if env is None else env, **{RUNNER_PID_ENV: str(os.getpid())})
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


class Supervisor:
    """The service processes of one run over Zenoh and their liveness: spawned (or, with
    ``attach``, started by somebody else), watched through their liveliness tokens (a
    role whose token disappears is ``lost``), started again by their restart policy (at
    most ``MAX_RESTARTS`` times each; ``on_restart(role)`` then re-synchronises it), and
    stopped with escalation.  ``wake`` is set whenever a role is lost."""

    def __init__(self, session, run_id: str, log_dir: Path, *, hosts=None, attach: bool = False,
                 restartable=(), on_restart=None, wake: threading.Event | None = None):
        self.session = session
        self.run_id = run_id
        self.log_dir = Path(log_dir)
        self.hosts = hosts
        self.attach = attach
        self.processes: list[ServiceProcess] = []
        self.watched: set = set()  # the roles of this run, once ready
        self.lost: dict = {}  # role -> monotonic time it was lost
        self._t0 = time.monotonic()
        self._alive_sub = None
        self.restartable: set = set(restartable)
        self.on_restart = on_restart
        self.restarts: list = []
        self._args: dict = {}
        self._wake = wake or threading.Event()

    def start(self, args: dict, timeout: float) -> None:
        """Spawn each role's process with its flags (``args``: role -> flags; none with
        ``attach``) and wait until every one is alive; then watch them."""
        if not self.attach:
            for role, flags in args.items():
                self._args[role] = flags
                self.processes.append(self._spawn(role))
        wait_alive(self.session, self.run_id, list(args), self.processes, timeout=timeout)
        self.watch(args)

    def mark_lost(self, role: str) -> None:
        self.lost.setdefault(role, time.monotonic())
        self._wake.set()

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

    def may_restart(self, role: str) -> bool:
        return (role in self.restartable and not self.attach
                and sum(r["role"] == role for r in self.restarts) < MAX_RESTARTS)

    def restart_lost(self) -> None:
        """Every lost role with a restart policy left is started again (one lost while
        another was being restarted too)."""
        while waiting := [r for r in self.lost if self.may_restart(r)]:
            self.restart(min(waiting, key=self.lost.get))

    def watch(self, roles) -> None:
        """From now on, a role whose liveliness token disappears is lost."""
        import zenoh

        self.watched = set(roles)
        self._t0 = time.monotonic()

        def on_token(sample) -> None:
            role = str(sample.key_expr).rsplit("/", 1)[-1]
            if role in self.watched and sample.kind == zenoh.SampleKind.DELETE:
                self.mark_lost(role)

        self._alive_sub = self.session.liveliness().declare_subscriber(topics.alive(self.run_id, "*"), on_token)
        # a token that went away between wait_alive and the subscriber is missing now
        missing = self.watched - alive_services(self.session, self.run_id, timeout=1.0)
        for role in missing:
            self.mark_lost(role)

    def lost_message(self, role: str, during: str = "") -> str:
        at = self.lost[role] - self._t0
        proc = next((p for p in self.processes if p.name == role), None)
        code = proc.popen.poll() if proc is not None else None
        how = f"its process exited with {code}" if code is not None else "its liveliness token disappeared"
        host = self.hosts.host_of(role) if self.hosts is not None else None
        where = f" on {host.describe()}" if host is not None else ""
        return f"service {role}{where} lost {at:.1f} s into the run{during}: {how}"

    def where(self) -> list[dict]:
        """The hosts the services ran on, when the run was split across hosts."""
        if self.hosts is None:
            return []
        return [{"name": h.name, "address": h.address, "namespace": h.namespace, "roles": list(h.roles)}
                for h in self.hosts.hosts]

    def kill(self) -> int:
        """Every service process still running killed now (SIGKILL to its group); how many."""
        running = [p for p in self.processes if p.alive()]
        for p in running:
            try:
                os.killpg(p.popen.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        return len(running)

    def post_mortem(self) -> list[str]:
        return [f"--- {p.name} exited with {p.popen.returncode}; end of its log:\n{p.tail()}"
                for p in self.processes if not p.alive()]

    def stop(self, shutdown) -> dict:
        """Stop the processes this run started: a lost one that is still there is hung or
        stopped and cannot shut down (killed); ``shutdown()`` asks the others to; then the
        escalation.  Their exit codes."""
        if self.attach:
            return {}
        # from here on a token that goes away is the shutdown asked for, not a loss: counted lost,
        # a service that failed on its way out (an exit code, a signal) was left out of the run's
        # verdict (``runner._unclean_exits`` leaves the lost ones to the error their loss made)
        self.watched = set()
        for p in self.processes:
            if p.name in self.lost and p.alive():
                try:
                    os.killpg(p.popen.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        shutdown()
        return stop(self.processes)

    def close(self) -> None:
        if self._alive_sub is not None:
            self._alive_sub.undeclare()
            self._alive_sub = None
