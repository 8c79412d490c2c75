"""What a run's processes cost to start and to end, apart from their work.

A run over Zenoh starts one service process per role and waits until every one is alive
(its liveliness token seen), and at its end asks them to shut down and waits until every
one has exited; a run in one process starts the MCAP writer's helper process and waits
for it at its first episode and at its end, and a pool of processes (the learn stage's,
the report's reads beside the run) is waited for when it shuts down.  Each is measured
here as the runner meets it:

- the six services of a run (robot, ft_sensor, recorder, teacher, phase_estimator,
  impedance_commander), started together: until all are alive; asked to shut down: until
  all have exited; and their CPU seconds from start to exit, each (``/proc``, read just
  before they are waited for), from ``--repeats`` starts;
- the writer's helper: from its spawn until its first file is open, and its close;
- a pool of two processes (``services.runtime.threads.process_map``) that imported what a
  fit imports: its shutdown.

    python bench/process_lifecycle.py [--repeats 3]

Prints the median and the range of each.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.transport import launch  # noqa: E402
from services.transport.service import request  # noqa: E402
from services.transport.session import ZenohOptions, open_session  # noqa: E402

ROLES = ("robot", "ft_sensor", "recorder", "teacher", "phase_estimator", "impedance_commander")
TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process still there (a zombie's included), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def services_once(folder: Path) -> dict:
    endpoint = f"tcp/127.0.0.1:{launch.free_port()}"
    session = open_session(ZenohOptions(listen=(endpoint,)))
    run_id = f"lifecycle{os.getpid()}x{time.monotonic_ns()}"
    common = ["--run-id", run_id, "--connect", endpoint]
    args = {role: common + (["--out-dir", str(folder)] if role == "recorder" else []) for role in ROLES}
    supervisor = launch.Supervisor(session, run_id, folder / "logs")
    try:
        t0 = time.monotonic()
        supervisor.start(args, 120)
        ready = time.monotonic() - t0

        def shutdown():
            for role in ROLES:
                request(session, run_id, role, "shutdown", timeout=5.0)

        cpu = {}
        t1 = time.monotonic()
        shutdown()
        # their CPU before they are reaped (a zombie's /proc/PID/stat still has it)
        while any(p.alive() for p in supervisor.processes) and time.monotonic() - t1 < 30:
            for p in supervisor.processes:
                try:
                    cpu[p.name] = cpu_seconds(p.popen.pid)
                except OSError:
                    pass
            time.sleep(0.002)
        codes = launch.stop(supervisor.processes)
        ended = time.monotonic() - t1
    finally:
        supervisor.close()
        session.close()
    if any(codes.values()):
        raise SystemExit(f"a service did not exit cleanly: {codes}")
    return {"ready": ready, "ended": ended, "cpu": cpu}


def writer_once(folder: Path) -> dict:
    from services.foxglove.tap import VisualRecordings
    from services.recordings.offload import WriterProcess

    t0 = time.monotonic()
    helper = WriterProcess(VisualRecordings(10.0))
    writer = helper.open(folder / "episode.mcap", run_id="lifecycle", episode_kind="demonstration", episode_index=0)
    opened = time.monotonic() - t0
    writer.finish()
    t1 = time.monotonic()
    helper.close()
    return {"open": opened, "close": time.monotonic() - t1}


def _imports_of_a_fit(_):
    import etar.em  # noqa: F401  (what a learn stage's process has loaded when it ends)

    return os.getpid()


def pool_once() -> dict:
    from services.runtime.threads import process_map

    with process_map(2) as pool_map:
        list(pool_map(_imports_of_a_fit, range(2)))
        t0 = time.monotonic()
    return {"shutdown": time.monotonic() - t0}


def spread(values) -> str:
    values = sorted(values)
    return f"{statistics.median(values):6.3f} s  ({values[0]:.3f}-{values[-1]:.3f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="starts of each (default 3)")
    repeats = parser.parse_args().repeats
    if repeats < 1:
        parser.error(f"--repeats must be >= 1, got {repeats}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        runs = [services_once(folder / f"services{i}") for i in range(repeats)]
        writers = [writer_once(folder) for _ in range(repeats)]
    pools = [pool_once() for _ in range(repeats)]
    print(f"{repeats} start(s) of each, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print(f"the six services of a run, started together, until all alive:  {spread(r['ready'] for r in runs)}")
    print(f"  asked to shut down, until all exited:                         {spread(r['ended'] for r in runs)}")
    for role in ROLES:
        print(f"  {role:20s} CPU from start to exit:                  {spread(r['cpu'][role] for r in runs)}")
    print(f"the MCAP writer's helper, spawned until its first file is open: {spread(w['open'] for w in writers)}")
    print(f"  its close:                                                    {spread(w['close'] for w in writers)}")
    print(f"a pool of two processes that imported a fit's modules, shutdown: {spread(p['shutdown'] for p in pools)}")


if __name__ == "__main__":
    main()
