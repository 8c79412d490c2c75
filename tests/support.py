"""What the tests share: the repository's scenarios as values, a run of one, and the
processes of a run."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from robot_sim.krc.link import FriConfig
from services.run.options import RunOptions
from services.run.runner import Runner
from services.scenario import Scenario, load_scenario
from services.transport.launch import PROGRAM_MODULE

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
# learned from smoke demonstrations started at [0.62, -0.06, 0.30], stored
SMOKE_MODEL = str(SCENARIOS / "models" / "smoke.json")


def scenario(name: str, changes: dict | None = None) -> Scenario:
    """``scenarios/<name>.yaml`` as a value, with ``changes`` ({path: value}, as
    ``Scenario.replace`` takes them) applied in order."""
    value = load_scenario(SCENARIOS / f"{name}.yaml")
    for path, new in (changes or {}).items():
        value = value.replace(path, new)
    return value


def hold(seconds: float, changes: dict | None = None) -> Scenario:
    """``scenarios/hold.yaml`` (the smoke reproduction held at its goal with the stored
    model, realtime) cut to ``seconds``."""
    return scenario("hold", {"reproduce.max_seconds": seconds, **(changes or {})})


def runner(value: Scenario, out, progress=print, **options) -> Runner:
    """A runner of ``value`` into ``out``; ``options`` as ``RunOptions`` takes them (no
    figures unless asked: most tests do not look at them)."""
    return Runner(value, RunOptions(out=str(out), **{"figures": False, **options}), progress)


def run(value: Scenario, out, progress=print, **options) -> dict:
    """``value`` run to its end: its report."""
    return runner(value, out, progress, **options).run()


def service_pid(role: str, run_id: str) -> int | None:
    """The pid of ``role``'s process in run ``run_id`` (``python -m services.cli.roles ROLE --run-id ...``)."""
    program = [PROGRAM_MODULE.encode(), role.encode()]
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        at = argv.index(program[0]) if program[0] in argv else -1
        if at >= 0 and argv[at:at + 2] == program and run_id.encode() in argv:
            return int(pid)
    return None


# the demonstrations' sample instants, 100 Hz on simulated time, written out here: the
# oracle below does not take it from the code it checks
SAMPLE_PERIOD_NS = 10_000_000


def recorded_samples(path, period_ns: int | None = SAMPLE_PERIOD_NS) -> dict:
    """An episode's recording as arrays, read with mcap's own reader and plain ``json``:
    an oracle that shares no code with ``load_demonstration`` (nor with the services'
    message decoding).

    The robot cycles that have a ``robot/state`` of the episode (not ``episode`` -1, the
    arm resting while the sensor is tared), an ``ft/wrench`` and a ``robot/contact``, the
    first message of each cycle, at the stamps that are multiples of ``period_ns`` (None:
    every cycle).  Arrays: ``seq``, ``stamp_ns``, ``pose`` (T, 12) msr_cart_pos,
    ``position`` (T, 3), ``R`` (T, 3, 3), ``safety`` (the KRC's), ``wrench`` (T, 6) the
    tared sensor's, sensor frame, ``wrench_base`` (T, 6) the same in base axes (R f,
    R tau), ``contact_force`` (T, 3) the physics', base frame, ``true_phase`` (T,)."""
    tables: dict[str, dict[int, dict]] = {"/robot/state": {}, "/ft/wrench": {}, "/robot/contact": {}}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            table = tables.get(channel.topic)
            if table is None:
                continue
            msg = json.loads(message.data)
            table.setdefault(msg["seq"], msg)
    states, wrenches, contacts = tables.values()
    cycles = sorted(seq for seq, s in states.items() if s["episode"] != -1 and seq in wrenches and seq in contacts
                    and (period_ns is None or s["stamp_ns"] % period_ns == 0))
    pose = np.array([states[s]["msr_cart_pos"] for s in cycles], dtype=np.float64).reshape(-1, 12)
    R = pose.reshape(-1, 3, 4)[:, :, :3]
    wrench = np.array([wrenches[s]["wrench"] for s in cycles], dtype=np.float64).reshape(-1, 6)
    return dict(
        seq=np.array(cycles, dtype=np.int64),
        stamp_ns=np.array([states[s]["stamp_ns"] for s in cycles], dtype=np.int64),
        pose=pose, position=pose.reshape(-1, 3, 4)[:, :, 3], R=R,
        safety=np.array([states[s]["safety"] for s in cycles], dtype=np.int64),
        wrench=wrench,
        wrench_base=np.concatenate([np.einsum("tij,tj->ti", R, wrench[:, :3]),
                                    np.einsum("tij,tj->ti", R, wrench[:, 3:])], axis=1),
        contact_force=np.array([contacts[s]["contact_force"] for s in cycles], dtype=np.float64).reshape(-1, 3),
        true_phase=np.array([contacts[s]["true_phase"] for s in cycles], dtype=np.int64))


# A realtime run over FRI/UDP needs a machine that can carry it.  The gauge is MuJoCo's own
# step of the arm pressed on a plate, ``mujoco.mj_step`` alone: C code no change here makes
# slower, so a regression in the project's own cycle still fails the tests instead of skipping
# them.  bench/sim_step.py's "MuJoCo step alone" row took 7.2 us on the reference 2-core VM
# (2026-12-02), but that row also runs the wrappers' apply and step; timed side by side on
# 2026-12-03 the bare mj_step took 0.62-0.70 of the row (3 pairs), so about 4.8 us there.  The
# robot's process took 57 % of a core over UDP on that VM (bench/realtime_load.py --wire udp):
# 570 us of CPU a 1 ms cycle, so on a machine 1.75 times slower the robot alone needs its whole
# cycle; 1.5 times leaves room for the remote and the Net F/T box on the same two cores:
# 1.5 x (0.62-0.70 x 7.2 us) = 6.7-7.5 us, and the limit is the top of that.  The gauge
# passed at 8-11 us on machines that then failed these tests (CI and this VM, 2026-12-03:
# an 11 us limit had been derived from the row, not from the bare step).
# ETAR_REALTIME_TESTS=force runs them whatever the gauge says.
REALTIME_MUJOCO_STEP_US = 7.5


@functools.cache
def mujoco_step_us() -> float:
    """MuJoCo's step of the arm pressed on a plate on this machine now, us: the best of three
    timings of 2000 steps (``mujoco.mj_step`` alone, no Python of ours in the loop)."""
    import time

    import mujoco

    from bench.sim_step import pressed_cell

    cell, q0, _, _ = pressed_cell()
    cell.place(q0)
    model, data = cell.sim.model, cell.sim.data
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(2000):
            mujoco.mj_step(model, data)
        best = min(best, (time.perf_counter() - t) / 2000 * 1e6)
    return best


# A shared virtual machine stalls now and then for several milliseconds (DESIGN.md; the bare loop of
# bench/realtime_load.py misses deadlines in the same runs), and a stall of a few cycles inside
# FRI's 100-cycle window drops command mode, as a real KRC does.  A realtime test is therefore run
# again once when its run fell short of 1 kHz by the run's own verdict (and the test judged it a
# stall: command mode entered, nearly every cycle answered in time), and skipped, with both
# verdicts, when the second attempt falls short too; anything else fails at once.  Holding the
# clock is bench/realtime_load.py's figure, measured against a bare loop on the same machine.
REALTIME_ATTEMPTS = 2


def realtime_attempts(attempt) -> None:
    """Run ``attempt(n)`` for n = 0, 1, ...: it returns None when its run held 1 kHz and every
    check passed, or the run's own line on how it fell short of the clock (its checks of what
    does not depend on timing made first).  Skips after ``REALTIME_ATTEMPTS`` shortfalls; with
    ETAR_REALTIME_TESTS=force it fails instead."""
    shortfalls = []
    for n in range(REALTIME_ATTEMPTS):
        why = attempt(n)
        if why is None:
            return
        shortfalls.append(why)
        print(f"attempt {n + 1} of {REALTIME_ATTEMPTS} fell short of the 1 kHz clock: {why}")
    lines = "; ".join(f"attempt {i + 1}: {w}" for i, w in enumerate(shortfalls))
    if os.environ.get("ETAR_REALTIME_TESTS") == "force":
        pytest.fail(f"this machine did not hold 1 kHz in {len(shortfalls)} attempts: {lines}")
    pytest.skip(f"this machine did not hold 1 kHz in {len(shortfalls)} attempts ({lines}); "
                f"bench/realtime_load.py measures it against a bare loop (ETAR_REALTIME_TESTS=force fails instead)")


# the share of an episode's FRI cycles answered in time above which a run that fell short of
# 1 kHz is judged a stalling machine rather than a remote that does not answer (CI's
# failure at de03c44 was a stall: 1.9 % missed)
STALL_ANSWERED = 0.9


def assert_a_stall(fri: dict, verdict: str) -> None:
    """Fail unless an episode's FRI figures (``fri`` of report.json) are those of a machine
    that stalled now and then: at least ``STALL_ANSWERED`` of its cycles answered in time,
    and command mode entered unless the misses came often enough to keep it out.  The KRC
    grants command mode after ``perfect_hold_cycles`` + ``window`` cycles without a miss
    (robot_sim.krc.link): a VM that stalls more often than that never gets there (CI on
    840142a: 158 of 15 000 cycles missed, never in command mode), whereas a KRC that
    withholds it from a remote answering nearly every cycle in time still fails here.
    ``verdict``: the run's own line on how it fell short."""
    total = fri["answered"] + fri["missed"]
    assert fri["answered"] >= STALL_ANSWERED * total, f"not a stall, too many cycles unanswered: {verdict}; {fri}"
    if fri["command_mode_entered"] < 1:
        link = FriConfig()
        clean = link.perfect_hold_cycles + link.window
        assert fri["missed"] * clean >= total, (f"not a stall, command mode never entered though a miss came only "
                                                f"every {total / max(fri['missed'], 1):.0f} cycles on average (it "
                                                f"needs {clean} without one): {verdict}; {fri}")


def require_realtime_machine() -> None:
    """Skip, saying why, where this machine is too slow to run the cell at 1 kHz realtime
    over UDP (``REALTIME_MUJOCO_STEP_US``), unless ETAR_REALTIME_TESTS=force."""
    if os.environ.get("ETAR_REALTIME_TESTS") == "force":
        return
    us = mujoco_step_us()
    if us > REALTIME_MUJOCO_STEP_US:
        pytest.skip(f"this machine takes {us:.1f} us for MuJoCo's step of the arm (best of 3 x 2000; about 4.8 on "
                    f"the reference VM): 1 kHz realtime over FRI/UDP needs at most {REALTIME_MUJOCO_STEP_US} us "
                    f"(ETAR_REALTIME_TESTS=force runs it anyway)")


def popen_as_from_a_terminal(argv: list, **kwargs) -> subprocess.Popen:
    """``subprocess.Popen(argv)`` with SIGINT at its default in the child, as a command
    typed at a terminal has it.  A shell that starts a job in the background without job
    control (``make test &`` in a script, nohup, some CI runners) starts it with SIGINT
    ignored, every process under it inherits that, and Python keeps an inherited SIGINT
    ignored: a Ctrl-C test would then send a signal nothing can see (the run went on to
    its end).  A Python handler, unlike SIG_IGN, is reset to the default across exec, so
    the parent holds one while it starts the child."""
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        return subprocess.Popen(argv, **kwargs)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return subprocess.Popen(argv, **kwargs)
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def trickling(addresses, every_s: float):
    """TCP connections to ``addresses`` that each send one byte every ``every_s`` and never
    a whole request (a slow or hostile client), closed on leaving."""
    import socket
    import threading

    sockets = [socket.create_connection(address, timeout=5) for address in addresses]
    stop = threading.Event()

    def trickle():
        while not stop.wait(every_s):
            for sock in sockets:
                try:
                    sock.send(b"G")
                except OSError:
                    pass
    threading.Thread(target=trickle, daemon=True).start()
    try:
        yield sockets
    finally:
        stop.set()
        for sock in sockets:
            sock.close()


def wait_until(condition, seconds: float, what: str, *, poll_s: float = 0.01, seen=None):
    """Poll ``condition()`` until it is truthy (returned) or ``seconds`` pass: then an
    AssertionError saying what was awaited, how long, and what was last seen (``seen()``,
    else the condition's last value).  The one wait the tests share."""
    import time

    deadline = time.monotonic() + seconds
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() >= deadline:
            last = seen() if seen is not None else value
            raise AssertionError(f"{what}: not within {seconds:g} s (last seen: {last!r})")
        time.sleep(poll_s)
