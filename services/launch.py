"""Starting and stopping service processes (what the runner and the tests use).

Each service runs as ``python -m services.<module>`` in its own process group,
with its output in a log file.  Readiness is its liveliness token, never a
sleep.  Stopping escalates SIGINT -> SIGTERM -> SIGKILL, each with a timeout.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from services.runtime.service import alive_services

MODULES = {
    "robot": "services.robot",
    "ft_sensor": "services.ft_sensor",
    "teacher": "services.teacher",
    "phase_estimator": "services.phase_estimator",
    "impedance_commander": "services.impedance_commander",
    "recorder": "services.recorder",
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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


def spawn(name: str, args: list[str], log_dir: Path, env: dict | None = None) -> ServiceProcess:
    log_dir.mkdir(parents=True, exist_ok=True)
    log_path = log_dir / f"{name}.log"
    log = open(log_path, "ab")
    popen = subprocess.Popen([sys.executable, "-m", MODULES[name], *args], stdout=log, stderr=subprocess.STDOUT,
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
