"""The floor of a run over Zenoh lockstep: the run's message graph with no work in it.

One process per role, as a run has them, each with a Zenoh session configured as the
services' are (``services.transport.session``), publishing and subscribing what that
role does, with payloads of the sizes a smoke run records; the handlers do nothing but
pair messages by ``seq`` and answer.  The robot opens cycle k (``robot/state``,
``robot/contact``) and waits for the cycle's answer (the teacher's in a demonstration,
the commander's in a reproduction), as the cycle engine does.  What this runs at is what
the messages alone cost: no run over Zenoh on this machine can go faster with this graph.

    python bench/zenoh_floor.py                      # demonstration and reproduction
    python bench/zenoh_floor.py --idle none           # the roles not in the episode unsubscribed

``--idle subscribed`` (the default) keeps the roles an episode does not need subscribed,
as a lockstep run did before 07f18be (the estimator and the commander in a demonstration,
the teacher in a reproduction; since then the teacher leaves, the other two stay);
``--idle none`` leaves them out, which is what dropping idle subscriptions could give at
most.  Prints cycles per second (real-time factor at 1 kHz)
and each process's CPU per cycle, from /proc.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh  # noqa: E402

from robot_sim.cycle import FRI_CYCLE_NS
from services.runtime.messages import (  # noqa: E402
    ESTIMATOR_PHASE, FT_WRENCH, ROBOT_COMMAND, ROBOT_CONTACT, ROBOT_STATE, TEACHER_WRENCH, estimator_instant)
from services.transport.launch import free_port  # noqa: E402
from services.transport.session import ZenohOptions, open_session  # noqa: E402
from services.transport.subscriptions import tenth_cycle  # noqa: E402

# bytes per message of a smoke run's recordings (demonstration_00, reproduction_00)
SIZES = {ROBOT_STATE.topic: 800, ROBOT_CONTACT.topic: 307, FT_WRENCH.topic: 270, TEACHER_WRENCH.topic: 231,
         ROBOT_COMMAND.topic: 602, ESTIMATOR_PHASE.topic: 161}
ROLES = ("robot", "ft_sensor", "teacher", "phase_estimator", "impedance_commander", "recorder")
# who works in which episode; the others are idle
WORKING = {"demonstration": {"robot", "ft_sensor", "teacher", "recorder"},
           "reproduction": {"robot", "ft_sensor", "phase_estimator", "impedance_commander", "recorder"}}
ANSWER = {"demonstration": TEACHER_WRENCH.topic, "reproduction": ROBOT_COMMAND.topic}


def payload(topic: str, seq: int) -> bytes:
    head = b'{"seq":%d,"stamp_ns":%d' % (seq, seq * FRI_CYCLE_NS)
    return head + b" " * max(0, SIZES[topic] - len(head) - 1) + b"}"


def seq_of(raw: bytes) -> int:
    return int(raw[7:raw.index(b",")])


def _cfg() -> tuple:
    """The ``--cfg`` pairs every session of the measurement takes (passed to the roles in the
    environment)."""
    return tuple(tuple(pair) for pair in json.loads(os.environ.get("FLOOR_CFG", "[]")))


def role_main(role: str, endpoint: str, run: str, episode: str, subscribed: bool) -> None:
    session = open_session(ZenohOptions(connect=(endpoint,), cfg=_cfg()))
    key = lambda topic: f"{run}/{topic}"  # noqa: E731
    # as services.transport.service.Service.publisher declares them
    express = {"express": True, "priority": zenoh.Priority.REAL_TIME} if os.environ["FLOOR_EXPRESS"] == "1" else {}
    pubs = {t: session.declare_publisher(key(t), congestion_control=zenoh.CongestionControl.BLOCK, **express)
            for t in SIZES}
    lock = threading.Lock()
    subs = []
    working = role in WORKING[episode]

    def sub(topic, fn):
        subs.append(session.declare_subscriber(key(topic), lambda s: fn(s.payload.to_bytes())))

    if role == "robot":
        answered = threading.Condition()
        last = [-1]

        def on_answer(raw):
            with answered:
                last[0] = max(last[0], seq_of(raw))
                answered.notify()
        sub(ANSWER[episode], on_answer)
        sub(FT_WRENCH.topic, lambda raw: None)
        sub(ESTIMATOR_PHASE.topic if episode == "reproduction" else ROBOT_COMMAND.topic, lambda raw: None)
    elif role == "ft_sensor":
        sub(ROBOT_CONTACT.topic, lambda raw: pubs[FT_WRENCH.topic].put(payload(FT_WRENCH.topic, seq_of(raw))))
    elif working or subscribed:
        pending: dict = {}

        def pair(topic, answer, needs):
            def on(raw):
                seq = seq_of(raw)
                if not working:
                    return
                with lock:
                    got = pending.setdefault(seq, set())
                    got.add(topic)
                    if needs(seq) <= got:
                        del pending[seq]
                        pubs[answer].put(payload(answer, seq))
            return on
        if role == "teacher":
            for t in (ROBOT_STATE.topic, ROBOT_CONTACT.topic):
                sub(t, pair(t, TEACHER_WRENCH.topic, lambda s: {ROBOT_STATE.topic, ROBOT_CONTACT.topic}))
        elif role == "phase_estimator":
            for t in (ROBOT_STATE.topic, FT_WRENCH.topic):
                # the real estimator skips the nine of ten from the raw bytes, in the callback
                sub(t, (lambda f: lambda raw: tenth_cycle(raw) and f(raw))(
                    pair(t, ESTIMATOR_PHASE.topic, lambda s: {ROBOT_STATE.topic, FT_WRENCH.topic})))
        elif role == "impedance_commander":
            need = lambda s: ({ROBOT_STATE.topic, ESTIMATOR_PHASE.topic}  # noqa: E731
                              if estimator_instant(s * FRI_CYCLE_NS) else {ROBOT_STATE.topic})
            for t in (ROBOT_STATE.topic, ESTIMATOR_PHASE.topic):
                sub(t, pair(t, ROBOT_COMMAND.topic, need))
        elif role == "recorder":
            everything = session.declare_subscriber(f"{run}/**", zenoh.handlers.FifoChannel(50_000))
            subs.append(everything)  # the subscriber itself: dropping it undeclares it
            fifo = everything.handler

            def drain():
                try:
                    while True:
                        fifo.recv().payload.to_bytes()
                        while (s := fifo.try_recv()) is not None:
                            s.payload.to_bytes()
                        time.sleep(0.005)
                except zenoh.ZError:
                    return
            threading.Thread(target=drain, daemon=True).start()
    token = session.liveliness().declare_token(key(f"alive/{role}"))
    if role == "robot":
        go = threading.Event()
        subs.append(session.declare_subscriber(key("bench/go"), lambda s: go.set()))
        ready = session.declare_publisher(key("bench/ready"))
        while not go.wait(0.2):
            ready.put(b"robot")  # again until the bench answers: one put may precede its subscriber
        cycles = int(os.environ["FLOOR_CYCLES"])
        done = session.declare_publisher(key("bench/done"))
        for k in range(cycles + 1):
            pubs[ROBOT_STATE.topic].put(payload(ROBOT_STATE.topic, k))
            pubs[ROBOT_CONTACT.topic].put(payload(ROBOT_CONTACT.topic, k))
            with answered:
                if not answered.wait_for(lambda: last[0] >= k, timeout=5.0):
                    done.put(b"timeout %d" % k)
                    break
            if k == 0:
                done.put(b"start")
        else:
            done.put(b"end")
    threading.Event().wait()  # until the bench kills this process
    del token


def ticks(pid: int) -> int:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])  # utime + stime


def measure(episode: str, subscribed: bool, cycles: int, express: bool) -> dict:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run = f"floor-{os.getpid()}-{time.time_ns()}"
    session = open_session(ZenohOptions(listen=(endpoint,), cfg=_cfg()))
    events: list = []
    cond = threading.Condition()

    def on_event(s):
        with cond:
            events.append((s.payload.to_bytes(), time.monotonic(), {p.args[3]: ticks(p.pid) for p in procs}))
            cond.notify_all()

    ready = threading.Event()
    alive = set()
    keep = [session.declare_subscriber(f"{run}/bench/done", on_event),
            session.declare_subscriber(f"{run}/bench/ready", lambda s: ready.set()),
            session.liveliness().declare_subscriber(f"{run}/alive/*", lambda s: alive.add(str(s.key_expr)))]
    env = dict(os.environ, FLOOR_CYCLES=str(cycles), FLOOR_EXPRESS="1" if express else "0")
    procs = [subprocess.Popen([sys.executable, __file__, "--as", role, endpoint, run, episode,
                               "1" if subscribed else "0"], env=env)
             for role in ROLES if subscribed or role in WORKING[episode]]
    try:
        deadline = time.monotonic() + 60
        while (len(alive) < len(procs) or not ready.is_set()) and time.monotonic() < deadline:
            time.sleep(0.05)
        if len(alive) < len(procs) or not ready.is_set():
            raise SystemExit(f"zenoh_floor: after 60 s, {len(alive)} of {len(procs)} roles alive, the robot "
                             f"{'ready' if ready.is_set() else 'not ready'}")
        time.sleep(1.0)  # declarations settle before the first cycle (a lockstep run waits likewise)
        session.put(f"{run}/bench/go", b"go")
        with cond:
            if not cond.wait_for(lambda: len(events) >= 2, timeout=cycles / 100 + 60):
                raise SystemExit(f"zenoh_floor: no end after {cycles} cycles: {events}")
        (what0, t0, cpu0), (what1, t1, cpu1) = events[:2]
        if what1 != b"end":
            raise SystemExit(f"zenoh_floor: the robot stopped: {what1.decode()}")
        tick_us = 1e6 / os.sysconf("SC_CLK_TCK")
        return {"cycles_per_s": cycles / (t1 - t0),
                "cpu_us_per_cycle": {r: (cpu1[r] - cpu0[r]) * tick_us / cycles for r in cpu0}}
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()
        del keep
        session.close()


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--as":
        role_main(sys.argv[2], sys.argv[3], sys.argv[4], sys.argv[5], sys.argv[6] == "1")
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycles", type=int, default=5000, help="FRI cycles per episode (default 5000, at least 1000)")
    ap.add_argument("--idle", choices=("subscribed", "none"), default="subscribed",
                    help="the roles an episode does not need: subscribed as today, or not running")
    ap.add_argument("--publishers", choices=("express", "batched"), default="express",
                    help="the 1 kHz publishers: express at REAL_TIME priority as the services declare "
                         "them (default), or Zenoh's defaults (batched, DATA priority)")
    ap.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                    help="a Zenoh configuration key with a JSON5 value for every session, as the services' "
                         "--cfg (repeatable), e.g. transport/unicast/lowlatency:true")
    ap.add_argument("--episodes", default="demonstration,reproduction",
                    help="which episode graphs to run (default both)")
    args = ap.parse_args()
    if args.cycles < 1000:
        # CPU time comes from /proc in 10 ms ticks: fewer cycles would blur it past use
        ap.error(f"--cycles {args.cycles}: at least 1000")
    pairs = []
    for item in args.cfg:
        key, sep, value = item.partition(":")
        if not sep or not key or not value:
            ap.error(f"--cfg {item!r}: expected KEY:VALUE")
        pairs.append((key, value))
    os.environ["FLOOR_CFG"] = json.dumps(pairs)
    try:
        open_session(ZenohOptions(listen=("tcp/127.0.0.1:0",), cfg=_cfg())).close()
    except ValueError as e:
        ap.error(str(e))
    episodes = [e.strip() for e in args.episodes.split(",") if e.strip()]
    for e in episodes:
        if e not in WORKING:
            ap.error(f"--episodes: unknown episode {e!r} (known: {', '.join(WORKING)})")
    print(f"the run's message graph over Zenoh lockstep, no work in the handlers; idle roles {args.idle}; "
          f"publishers {args.publishers}; cfg {' '.join(args.cfg) or 'none'}; "
          f"{args.cycles} cycles; {os.cpu_count()} CPUs; CPU time in /proc ticks, "
          f"+-{1e6 / os.sysconf('SC_CLK_TCK') / args.cycles:.0f} us per cycle per process")
    for episode in episodes:
        r = measure(episode, args.idle == "subscribed", args.cycles, args.publishers == "express")
        cpu = r["cpu_us_per_cycle"]
        print(f"  {episode:14s} {r['cycles_per_s']:7.0f} cycles/s = {r['cycles_per_s'] / 1000:.2f}x real time; "
              f"{1e6 / r['cycles_per_s']:.0f} us per cycle; CPU us per cycle: "
              + ", ".join(f"{k} {v:.0f}" for k, v in sorted(cpu.items(), key=lambda kv: -kv[1]))
              + f"; all {sum(cpu.values()):.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
