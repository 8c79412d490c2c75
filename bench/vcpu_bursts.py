"""Does this machine run a fixed piece of work in the same time every millisecond?

    python bench/vcpu_bursts.py [--seconds 10] [--cpu 1] [--work-us 150] [--spin] [--cpu-latency-qos]

A 1 kHz loop on one CPU under SCHED_FIFO (where permitted) does the same small
numpy work every cycle (about ``--work-us`` microseconds: 6x6 solves, the size of
the robot's own linear algebra) and sleeps to the next deadline (``--spin``: spins
instead; ``--cpu-latency-qos``: idle CPUs poll, /dev/cpu_dma_latency 0).  Only how
long the same work takes is measured, not the wake-ups.  On
bare metal its time barely moves.  On a virtual machine whose host is shared,
the vCPU runs several times slower for milliseconds at a time; a cycle whose
work takes 3x its median is "slow", and a run of slow cycles is a burst.  The
robot's FRI cycle is ~250-350 us of work in its own process: a burst at 3-5x
pushes it past its 1 ms deadline, whatever the software does.

With ``--spin`` the CPU is busy all the time, so the kernel's realtime throttling
(sched_rt_runtime_us, 950 ms of each second) stops the loop for ~50 ms once a
second under SCHED_FIFO; the host, too, sees a vCPU that never idles.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--cpu", type=int, default=max(os.sched_getaffinity(0)))
    p.add_argument("--work-us", type=float, default=150.0)
    p.add_argument("--spin", action="store_true", help="spin to each deadline instead of sleeping")
    p.add_argument("--cpu-latency-qos", action="store_true", help="hold /dev/cpu_dma_latency at 0 (root)")
    args = p.parse_args()
    if args.cpu_latency_qos:
        import struct

        qos = os.open("/dev/cpu_dma_latency", os.O_WRONLY)  # held while the file is open
        os.write(qos, struct.pack("i", 0))
    os.sched_setaffinity(0, {args.cpu})
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(60))
        fifo = "SCHED_FIFO 60"
    except (PermissionError, OSError):
        fifo = "ordinary (SCHED_FIFO not permitted)"
    rng = np.random.default_rng(0)
    a, b = rng.random((6, 6)) + 6 * np.eye(6), rng.random(6)

    def solves(n):
        s = 0.0
        for _ in range(n):
            s += float(np.linalg.solve(a, b)[0])
        return s

    t = time.perf_counter_ns()
    solves(2000)
    per = (time.perf_counter_ns() - t) / 2000
    n = max(1, round(args.work_us * 1e3 / per))
    cycles = int(args.seconds * 1000)
    work = np.empty(cycles)
    lateness = np.empty(cycles)
    deadline = time.monotonic_ns()
    for k in range(cycles):
        deadline += 1_000_000
        t = time.perf_counter_ns()
        solves(n)
        work[k] = (time.perf_counter_ns() - t) / 1e3
        if not args.spin:
            left = deadline - time.monotonic_ns()
            if left > 0:
                time.sleep(left / 1e9)
        while (now := time.monotonic_ns()) < deadline:
            pass
        if now > deadline + 1_000_000:
            deadline = now  # after an overrun: start again from now, no burst of catching up
        lateness[k] = (now - deadline) / 1e3
    med = float(np.median(work))
    slow = work > 3 * med
    late = lateness > 1000
    runs, run = [], 0
    for s in slow:
        run = run + 1 if s else 0
        if run == 1:
            runs.append(1)
        elif run > 1:
            runs[-1] = run
    print(f"CPU {args.cpu}, {fifo}, {cycles} cycles of {n} solves ({med:.0f} us median work), "
          f"{'spinning' if args.spin else 'sleeping'} to each deadline"
          f"{', idle CPUs polling' if args.cpu_latency_qos else ''}")
    print(f"work us: p50 {med:.0f}, p99 {np.percentile(work, 99):.0f}, p99.9 {np.percentile(work, 99.9):.0f}, "
          f"max {work.max():.0f}")
    print(f"slow cycles (work > 3x median): {int(slow.sum())} of {cycles} = {100 * slow.mean():.2f} %, in "
          f"{len(runs)} bursts, longest {max(runs, default=0)} cycles; "
          f"work > 1 ms: {int((work > 1000).sum())}")
    print(f"wake-ups more than 1 ms late: {int(late.sum())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
