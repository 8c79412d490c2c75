"""Our link vs a bare Zenoh ping-pong of the same payload, in the same run.

    python bench/zenoh_link.py [--n 3000]

Two processes on loopback.  Bare: raw bytes of a robot_state's size, echoed
back.  Ours: the robot_state message encoded, published with the services'
settings (express, REAL_TIME priority), decoded and checked by the receiver,
answered with an encoded robot_command that is decoded in turn - what the
robot <-> commander link does every FRI cycle.  Prints one-way latency
(CLOCK_MONOTONIC, same host) and round trip, paced at 1 kHz.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import threading
import time

import numpy as np


def _session(listen=None, connect=None):
    from services.transport.session import ZenohOptions, open_session

    return open_session(ZenohOptions(listen=tuple(listen or ["tcp/127.0.0.1:0"]), connect=tuple(connect or [])))


def ponger(endpoint, mode, ready, stop):
    import zenoh

    from services.runtime.messages import ROBOT_COMMAND, ROBOT_STATE

    s = _session(connect=[endpoint])
    pub = s.declare_publisher(f"bench/{mode}/pong", express=True, priority=zenoh.Priority.REAL_TIME)
    cmd = dict(cart_pos=np.eye(3, 4).ravel(), cart_stiffness=np.zeros(6), cart_damping=np.full(6, 0.7),
               add_tcp_ft=np.zeros(6), requested_mode=2, phase=1, estimate_seq=-1, goal_reached=False, hold="", episode=0)

    def on_ping(sample):
        raw = sample.payload.to_bytes()
        if mode == "bare":
            pub.put(raw)
        else:
            m = ROBOT_STATE.decode(raw)
            pub.put(ROBOT_COMMAND.encode(seq=m["seq"], stamp_ns=m["stamp_ns"], sent_ns=time.monotonic_ns(), **cmd))

    sub = s.declare_subscriber(f"bench/{mode}/ping", on_ping)
    ready.set()
    stop.wait()
    sub.undeclare()
    s.close()


def measure(mode, n):
    import zenoh

    from services.transport.launch import free_port
    from services.runtime.messages import ROBOT_COMMAND, ROBOT_STATE

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    s = _session(listen=[endpoint])
    # spawn, not fork: a forked child inherits Zenoh's runtime threads half-alive and hangs
    ctx = mp.get_context("spawn")
    ready, stop = ctx.Event(), ctx.Event()
    p = ctx.Process(target=ponger, args=(endpoint, mode, ready, stop))
    p.start()
    ready.wait(30)
    time.sleep(0.5)
    got = threading.Event()
    box = {}

    def on_pong(sample):
        box["recv"] = time.monotonic_ns()
        raw = sample.payload.to_bytes()
        box["sent_back"] = ROBOT_COMMAND.decode(raw)["sent_ns"] if mode == "ours" else None
        got.set()

    sub = s.declare_subscriber(f"bench/{mode}/pong", on_pong)
    pub = s.declare_publisher(f"bench/{mode}/ping", express=True, priority=zenoh.Priority.REAL_TIME)
    z7, z12, z6 = np.zeros(7), np.eye(3, 4).ravel(), np.zeros(6)
    template = ROBOT_STATE.encode(seq=0, stamp_ns=0, sent_ns=0, reflected_seq=0, fri_state=2, fri_quality=3,
                                  control_mode=2, msr_jnt_pos=z7, msr_cart_pos=z12, est_ext_tcp_ft=z6,
                                  answer_rate=1.0, latency_s=0.0, jitter_s=0.0, miss_rate=0.0, safety=0,
                                  gravity_compensation=False, episode=0)
    rtt, back = [], []
    time.sleep(0.5)
    next_t = time.monotonic()
    for k in range(n):
        next_t += 0.001
        got.clear()
        t0 = time.monotonic_ns()
        if mode == "bare":
            pub.put(template)
        else:
            pub.put(ROBOT_STATE.encode(seq=k, stamp_ns=k, sent_ns=t0, reflected_seq=k, fri_state=2, fri_quality=3,
                                       control_mode=2, msr_jnt_pos=z7, msr_cart_pos=z12, est_ext_tcp_ft=z6,
                                       answer_rate=1.0, latency_s=0.0, jitter_s=0.0, miss_rate=0.0, safety=0,
                                       gravity_compensation=False, episode=0))
        if got.wait(1.0):
            rtt.append(box["recv"] - t0)
            if box["sent_back"] is not None:
                back.append(box["recv"] - box["sent_back"])
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    stop.set()
    p.join(10)
    sub.undeclare()
    s.close()
    return np.array(rtt) / 1e3, np.array(back) / 1e3, len(template)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=3000)
    args = parser.parse_args()
    rows = {}
    for mode in ("bare", "ours"):
        rows[mode] = measure(mode, args.n)
    size = rows["bare"][2]
    print(f"{args.n} exchanges at 1 kHz, payload {size} B (robot_state), two processes on loopback")
    print(f"{'link':<6} {'answered':>8} {'RTT p50':>8} {'p99':>8} {'max':>8}   {'one-way back p50':>16} {'p99':>7}")
    for mode, (rtt, back, _) in rows.items():
        ow = f"{np.percentile(back, 50):>16.0f} {np.percentile(back, 99):>7.0f}" if back.size else f"{'-':>16} {'-':>7}"
        print(f"{mode:<6} {rtt.size:>8} {np.percentile(rtt, 50):>8.0f} {np.percentile(rtt, 99):>8.0f} "
              f"{rtt.max():>8.0f}   {ow}")
    ratio = np.percentile(rows["ours"][0], 50) / np.percentile(rows["bare"][0], 50)
    print(f"ours / bare round trip (p50): {ratio:.2f}  (target: within 2x)")


if __name__ == "__main__":
    main()
