"""A 1 kHz loop in our runtime vs a bare absolute-deadline loop, in the same run.

    python bench/loop_1khz.py [--seconds 10] [--sched-fifo]

Both loops run at the same time in two processes: the bare one only sleeps to
absolute deadlines and records its lateness; ours (``AbsoluteDeadlineTimer`` +
``LoopTiming``) also does a cycle's worth of work: encode and publish a
robot_state-sized message to itself over a Zenoh session.  The machine's own
stalls hit both, so the comparison is what our runtime adds.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time

import numpy as np


def bare_loop(seconds, fifo, queue):
    from services.runtime.loop import set_timer_slack, try_sched_fifo

    used = try_sched_fifo() if fifo else False
    set_timer_slack(1)
    period = 1_000_000
    late = []
    deadline = time.monotonic_ns() + period
    end = deadline + int(seconds * 1e9)
    while deadline < end:
        now = time.monotonic_ns()
        if deadline > now:
            time.sleep((deadline - now) / 1e9)
        wake = time.monotonic_ns()
        late.append(wake - deadline)
        deadline += period
        if wake >= deadline:  # skip what was missed, as ours does
            deadline += ((wake - deadline) // period + 1) * period
    queue.put(("bare", used, np.array(late)))


def our_loop(seconds, fifo, queue):
    from services.runtime.loop import AbsoluteDeadlineTimer, LoopTiming, set_timer_slack, try_sched_fifo
    from services.runtime.messages import ROBOT_STATE
    from services.transport.session import ZenohOptions, open_session

    used = try_sched_fifo() if fifo else False
    set_timer_slack(1)
    session = open_session(ZenohOptions(listen=("tcp/127.0.0.1:0",)))
    pub = session.declare_publisher("bench/loop/state")
    timing = LoopTiming(1_000_000)
    timer = AbsoluteDeadlineTimer(1_000_000)
    z7, z12, z6 = np.zeros(7), np.eye(3, 4).ravel(), np.zeros(6)
    n = int(seconds * 1000)
    late = []
    for k in range(n):
        deadline, wake = timer.wait()
        t0 = time.monotonic_ns()
        pub.put(ROBOT_STATE.encode(seq=k, stamp_ns=k * 1_000_000, sent_ns=t0, reflected_seq=k, fri_state=2,
                                   fri_quality=3, control_mode=2, msr_jnt_pos=z7, msr_cart_pos=z12,
                                   est_ext_tcp_ft=z6, answer_rate=1.0, latency_s=0.0, jitter_s=0.0, miss_rate=0.0,
                                   safety=0, gravity_compensation=False, episode=0))
        t1 = time.monotonic_ns()
        timing.record(wake - deadline, t1 - t0, t1 > deadline + 1_000_000)
        late.append(wake - deadline)
    session.close()
    queue.put(("ours", used, np.array(late)))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--sched-fifo", action="store_true")
    args = parser.parse_args()
    q = mp.Queue()
    procs = [mp.Process(target=f, args=(args.seconds, args.sched_fifo, q)) for f in (bare_loop, our_loop)]
    for p in procs:
        p.start()
    results = {}
    for _ in procs:
        name, fifo, late = q.get()
        results[name] = (fifo, late)
    for p in procs:
        p.join()
    print(f"1 kHz for {args.seconds:.0f} s, SCHED_FIFO requested: {args.sched_fifo}")
    print(f"{'loop':<6} {'fifo':>5} {'cycles':>7} {'p50 us':>8} {'p99 us':>8} {'p99.9 us':>9} {'max us':>9} "
          f"{'late>500us':>11} {'late>1ms':>9}")
    for name in ("bare", "ours"):
        fifo, late = results[name]
        us = late / 1e3
        print(f"{name:<6} {str(fifo):>5} {len(us):>7} {np.percentile(us, 50):>8.0f} {np.percentile(us, 99):>8.0f} "
              f"{np.percentile(us, 99.9):>9.0f} {us.max():>9.0f} {int(np.sum(us > 500)):>11} "
              f"{int(np.sum(us > 1000)):>9}")


if __name__ == "__main__":
    main()
