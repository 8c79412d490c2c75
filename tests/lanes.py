"""``make test``'s two lanes, at the same time on CI's two cores.

    python -m tests.lanes          (make test runs it once the set-up is done)

The ``serial`` tests (the realtime clock, 1 kHz over UDP, a browser's fixed waits,
signals timed against a run) run one at a time in the foreground and print as they go.
They keep about one core of two busy.  Beside them, every other test runs two at a time
(pytest-xdist) under SCHED_IDLE: a process of that lane gets a CPU only when nothing
else wants it, so it takes the serial lane's slack without delaying a realtime run's
wake-ups (under ``nice 19`` instead, a restarted estimator came back too late for the
commander's patience).  The lane's processes inherit it: its Zenoh services, its
workers' threads (numba's and OpenBLAS' at one each: two workers' threads spinning
against each other made EM 20 times slower).

The shared lane's output goes to ``out/make-test-shared.log``; it is printed once the
serial lane is over, then followed to its end.  The exit status is 0 only when both
lanes passed (pytest's 5, no test collected, fails too).  Ctrl-C reaches both lanes;
a second one kills what is left of them.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED_LOG = ROOT / "out" / "make-test-shared.log"
PYTEST = [sys.executable, "-m", "pytest", "-q"]
SHARED = [*PYTEST, "-n", "2", "--dist", "loadscope", "--no-loadscope-reorder", "-m", "not serial"]
SERIAL = [*PYTEST, "-m", "serial"]


def _idle() -> None:
    """In the shared lane's first process, before it runs pytest: SCHED_IDLE, or the lowest
    nice value where that policy does not exist."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        os.nice(19)


def _follow(log, proc: subprocess.Popen) -> None:
    """Copy what the shared lane writes to stdout until it exits."""
    while True:
        chunk = log.read()
        if chunk:
            sys.stdout.write(chunk)
            sys.stdout.flush()
        elif proc.poll() is not None:
            return
        else:
            time.sleep(0.5)


class _Terminated(KeyboardInterrupt):
    """SIGTERM (a CI's time limit): unlike Ctrl-C, it did not reach the serial lane too."""


def _terminate(signum, frame):
    raise _Terminated


def main() -> int:
    SHARED_LOG.parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    with open(SHARED_LOG, "w") as out:
        # its own process group: Ctrl-C is forwarded to it, and a second one kills it whole
        shared = subprocess.Popen(SHARED, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT,
                                  preexec_fn=_idle, start_new_session=True)
    print(f"make test: the tests that share the machine run two at a time beside the serial ones "
          f"(their output: {SHARED_LOG.relative_to(ROOT)}, printed when the serial ones are over)", flush=True)
    serial = None
    signal.signal(signal.SIGTERM, _terminate)
    try:
        serial = subprocess.Popen(SERIAL, cwd=ROOT)
        serial.wait()
        print(f"\nmake test: the tests run two at a time ({SHARED_LOG.relative_to(ROOT)}):", flush=True)
        with open(SHARED_LOG, errors="replace") as log:
            _follow(log, shared)
    except KeyboardInterrupt as exc:
        return _interrupted(shared, serial, terminated=isinstance(exc, _Terminated))
    print(f"make test: exit {shared.returncode} for the tests run two at a time, "
          f"{serial.returncode} for the serial ones", flush=True)
    return 0 if shared.returncode == 0 and serial.returncode == 0 else 1


def _interrupted(shared: subprocess.Popen, serial: subprocess.Popen | None, terminated: bool) -> int:
    """Ctrl-C: the serial lane has it from the terminal, the shared lane (its own group) is
    told; SIGTERM: both are told.  They get 30 s to stop; a second Ctrl-C, or the 30 s,
    kills them."""
    print("\nmake test: interrupted; stopping both lanes (Ctrl-C again kills them)", file=sys.stderr, flush=True)
    procs = [p for p in (shared, serial) if p is not None]
    try:
        os.killpg(shared.pid, signal.SIGINT)
        if terminated and serial is not None and serial.poll() is None:
            serial.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and any(p.poll() is None for p in procs):
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    for proc in procs:
        if proc.poll() is None:
            try:
                if proc is shared:
                    os.killpg(proc.pid, signal.SIGKILL)  # its workers and what they started in its group
                else:
                    proc.kill()
            except ProcessLookupError:
                pass
    print(f"make test: interrupted (the shared lane's output so far: {SHARED_LOG.relative_to(ROOT)})",
          file=sys.stderr)
    return 130


if __name__ == "__main__":
    sys.exit(main())
