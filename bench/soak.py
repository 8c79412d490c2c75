"""Soak: the full service set on the realtime clock for ten minutes, and whether anything drifts.

    python bench/soak.py [--minutes 10] [--out DIR]

Runs scenarios/hold.yaml for ``--minutes`` over Zenoh on loopback: the robot at
1 kHz in FRI command mode, answered every cycle by the impedance commander,
with the F/T sensor, the phase estimator (100 Hz) and the recorder, the
reproduction held at its goal after the first seconds.  Every 10 s it reads
each service's resident set size (/proc/PID/status VmRSS).  Afterwards it reads
the recording back and gives, per minute of the run:

- the FRI answer latency, measurement sent -> command sent (robot_state.sent_ns
  to robot_command.sent_ns of the same cycle, one clock): p50, p99, max;
- the share of cycles with no command sent within the 1 ms cycle;
- each service's RSS at the minute's end.

"Flat" is what a soak must show: no growth of memory, no latency creeping up.
The last line says per service how much its RSS grew from the end of the first
minute (after start-up, imports and the first episode's allocations) to the end.
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.runtime.messages import ROBOT_COMMAND, ROBOT_STATE  # noqa: E402

SEQ_SENT = re.compile(rb'^\{"seq":(\d+),"stamp_ns":\d+,"sent_ns":(\d+)')


def rss_kib(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def sample_rss(runner, stop: threading.Event, samples: list, every: float = 10.0) -> None:
    t0 = None
    while not stop.is_set():
        procs = runner.cell.processes if runner.ready.is_set() else []
        if procs:
            t0 = t0 or time.monotonic()
            samples.append((time.monotonic() - t0, {p.name: rss_kib(p.popen.pid) for p in procs}))
        stop.wait(every)


def per_minute(path: Path, t_start_ns: int) -> list:
    from services.recordings.reader import read_episode

    sent_state, sent_cmd = {}, {}
    for m in read_episode(path).messages:
        if m.topic in (ROBOT_STATE.channel, ROBOT_COMMAND.channel):
            g = SEQ_SENT.match(m.payload)
            if g:
                (sent_state if m.topic == ROBOT_STATE.channel else sent_cmd)[int(g.group(1))] = int(g.group(2))
    rows = []
    seqs = np.array(sorted(sent_state))
    t_state = np.array([sent_state[s] for s in seqs])
    minute = (t_state - t_start_ns) // 60_000_000_000
    for k in range(int(minute.max()) + 1):
        sel = seqs[minute == k]
        lat = np.array([sent_cmd[s] - sent_state[s] for s in sel if s in sent_cmd], dtype=np.float64) / 1e3
        late = sum(1 for s in sel if s not in sent_cmd or sent_cmd[s] - sent_state[s] > 1_000_000)
        rows.append(dict(minute=k, cycles=int(sel.size), p50_us=float(np.percentile(lat, 50)) if lat.size else None,
                         p99_us=float(np.percentile(lat, 99)) if lat.size else None,
                         max_us=float(lat.max()) if lat.size else None, late_share=late / max(1, sel.size)))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--out", help="run directory (default: a temporary one)")
    args = parser.parse_args()
    if not args.minutes > 0:
        parser.error(f"--minutes must be > 0, got {args.minutes}")

    from hold import hold_scenario
    from services.run.options import RunOptions
    from services.run.runner import Runner

    out = Path(args.out or tempfile.mkdtemp(prefix="soak-"))
    out.mkdir(parents=True, exist_ok=True)
    runner = Runner(hold_scenario(args.minutes * 60), RunOptions(out=str(out), run_id=f"soak-{uuid.uuid4().hex[:8]}"),
                    progress=lambda m: print(m, file=sys.stderr, flush=True))
    stop, samples = threading.Event(), []
    sampler = threading.Thread(target=sample_rss, args=(runner, stop, samples), daemon=True)
    sampler.start()
    try:
        report = runner.run()
    finally:
        stop.set()
        sampler.join(15)
    print(f"soak: {args.minutes:g} min of scenarios/hold.yaml on the realtime clock over Zenoh, run dir {out}")
    if report["error"]:
        print(f"the run reported: {report['error']}")
    (rp,) = report["reproductions"]
    loop = report["timing"]["robot_loop"]["per_episode"][-1]
    rows = per_minute(out / rp["path"], loop["wall_start_ns"])
    roles = sorted({r for _, d in samples for r in d})
    print(f"{'minute':>6} {'cycles':>7} {'p50 us':>7} {'p99 us':>7} {'max us':>8} {'late':>7}  "
          + "  ".join(f"{r[:10]:>10}" for r in roles) + "   (RSS MiB at the minute's end)")
    samples = [(t, d) for t, d in samples if all(d.values())]  # the services' own, not after they ended
    for row in rows:
        if row["cycles"] < 1000:
            continue  # the run's last few cycles, not a minute
        at = [d for t, d in samples if t <= 60 * (row["minute"] + 1)]
        rss = at[-1] if at else {}
        print(f"{row['minute']:6d} {row['cycles']:7d} {row['p50_us'] or 0:7.0f} {row['p99_us'] or 0:7.0f} "
              f"{row['max_us'] or 0:8.0f} {row['late_share']:7.2%}  "
              + "  ".join(f"{(rss.get(r) or 0) / 1024:10.1f}" for r in roles))
    first = next((d for t, d in samples if t >= 60), samples[0][1] if samples else {})
    last = samples[-1][1] if samples else {}
    print("RSS growth from the end of minute 0 to the end: " + ", ".join(
        f"{r} {((last.get(r) or 0) - (first.get(r) or 0)) / 1024:+.1f} MiB" for r in roles))
    print(f"FRI over the run: {rp['fri']}; robot loop misses {loop['misses']} of {loop['cycles']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
