"""``make test``'s lanes, on CI's two cores.

    python -m tests.lanes          (make test runs it once the set-up is done)

First the tests marked ``alone`` (1 kHz against the wall clock, timings a busy machine
stretches), one at a time with nothing beside them.  Then two lanes at once: the other
``serial`` tests (a browser's fixed waits, signals timed against a run) one at a time in
the foreground, about one core of two busy; and beside them every test that is not
serial, two at a time (pytest-xdist), under SCHED_IDLE: a process of that lane gets a
CPU only when nothing else wants it, so it takes the serial lane's slack without
delaying it.  The lane's processes inherit the policy (its Zenoh services, podman's
containers); its workers' numba and OpenBLAS threads are one each (two workers'
threads spinning against each other made EM 20 times slower).  Beside the shared lane
even under SCHED_IDLE, MuJoCo's step measured 8.6 us against 4.8 alone, and the
realtime tests skipped: hence ``alone``.

The shared lane's output goes to ``out/make-test-shared.log``; it is printed once the
serial lane is over, then followed to its end.  The exit status is 0 only when all three
passed (pytest's 5, no test collected, fails too).  Ctrl-C reaches every lane running;
a second one kills what is left of them.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED_LOG = ROOT / "out" / "make-test-shared.log"
# each lane ends with its ten longest tests: where CI's minutes went, in its own log
PYTEST = [sys.executable, "-m", "pytest", "-q", "--durations=10", "--durations-min=5"]
SHARED = [*PYTEST, "-n", "2", "--dist", "loadscope", "--no-loadscope-reorder", "-m", "not serial"]
ALONE = [*PYTEST, "-m", "alone"]
SERIAL = [*PYTEST, "-m", "serial and not alone"]


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
    """SIGTERM (a CI's time limit): unlike Ctrl-C, it did not reach the foreground lane too."""


def _terminate(signum, frame):
    raise _Terminated


def _start_shared() -> subprocess.Popen:
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    with open(SHARED_LOG, "w") as out:
        # its own process group: Ctrl-C is forwarded to it, and a second one kills it whole
        return subprocess.Popen(SHARED, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT,
                                preexec_fn=_idle, start_new_session=True)


def main(argv=None) -> int:
    from etar.parsing import OneLineErrorParser

    OneLineErrorParser(prog="python -m tests.lanes", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter).parse_args(argv)
    SHARED_LOG.parent.mkdir(parents=True, exist_ok=True)
    log = SHARED_LOG.relative_to(ROOT)
    signal.signal(signal.SIGTERM, _terminate)
    alone = serial = shared = None
    try:
        print("make test: the tests that need the machine to themselves, one at a time", flush=True)
        alone = subprocess.Popen(ALONE, cwd=ROOT)
        alone.wait()
        shared = _start_shared()
        print(f"make test: the other serial tests, one at a time, and beside them the rest two at a time "
              f"(their output: {log}, printed when the serial ones are over)", flush=True)
        serial = subprocess.Popen(SERIAL, cwd=ROOT)
        serial.wait()
        print(f"\nmake test: the tests run two at a time ({log}):", flush=True)
        with open(SHARED_LOG, errors="replace") as out:
            _follow(out, shared)
    except KeyboardInterrupt as exc:
        return _interrupted([p for p in (alone, serial) if p is not None], shared,
                            terminated=isinstance(exc, _Terminated))
    codes = (alone.returncode, serial.returncode, shared.returncode)
    print(f"make test: exit {codes[0]} for the tests run alone, {codes[1]} for the other serial ones, "
          f"{codes[2]} for the tests run two at a time", flush=True)
    return 0 if codes == (0, 0, 0) else 1


def _interrupted(foreground: list, shared: subprocess.Popen | None, terminated: bool) -> int:
    """Ctrl-C: the foreground lane has it from the terminal, the shared lane (its own group)
    is told; SIGTERM: both are told.  They get 30 s to stop; a second Ctrl-C, or the 30 s,
    kills them."""
    print("\nmake test: interrupted; stopping the lanes (Ctrl-C again kills them)", file=sys.stderr, flush=True)
    procs = [*foreground, *([shared] if shared is not None else [])]
    try:
        if shared is not None and shared.poll() is None:
            try:
                os.killpg(shared.pid, signal.SIGINT)
            except ProcessLookupError:
                pass  # it ended between the poll and the signal
        for proc in foreground:
            if terminated and proc.poll() is None:
                proc.send_signal(signal.SIGINT)
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
