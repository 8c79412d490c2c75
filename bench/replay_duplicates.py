"""A foreign Zenoh peer re-publishes a share of a run's 1 kHz messages: does any result change?

Runs the smoke scenario twice over Zenoh on the lockstep clock with the same seed:
once clean, once while a peer of the run (the one every service connects to, as to
a router) re-publishes ``--share`` of every message on the FRI chain's topics,
each both at once (an exact copy) and ``--late-ms`` later (a stale copy).  The
receivers drop duplicates and older messages by seq, so the lockstep results must
be the same to the last digit; the table says what was replayed, what the services
dropped, and the results side by side.

``--forge``: the peer also forges, every 0.3 s and twice each, a well-formed
robot/command 997 cycles past its last (seq 1, 998, ...: from the start, so a receiver
may see the forger's stream before the run's own), asking for a control mode FRI has
not (7), stamped sent_ns 1, beside garbage on robot/command and ft/wrench.  The robot
must drop the forgeries as past its latest measurement (``ahead``), count the garbage
and the stamps off its clock, and the results still be the clean run's.

``--forge-measurements`` (with ``--forge``): the forger also publishes a well-formed
robot/state and robot/contact with each forged command's seq.  What no receiver can
tell from the robot's own (they do not know its publisher): this shows what they cost
(the results are not expected to be the clean run's; the exit status says whether they were).

    python bench/replay_duplicates.py [--share 0.1] [--late-ms 30] [--seed 0] [--forge [--forge-measurements]]
"""

from __future__ import annotations

import argparse
import heapq
import random
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.transport.launch import free_port  # noqa: E402
from services.run.options import RunOptions  # noqa: E402
from services.run.runner import run  # noqa: E402
from services.scenario import load_scenario  # noqa: E402
from services.runtime import topics  # noqa: E402
from services.transport.session import ZenohOptions, open_session  # noqa: E402
from services.runtime.messages import (  # noqa: E402
    ESTIMATOR_PHASE, FT_WRENCH, ROBOT_COMMAND, ROBOT_CONTACT, ROBOT_STATE)

TOPICS = (ROBOT_STATE.topic, ROBOT_CONTACT.topic, FT_WRENCH.topic, ESTIMATOR_PHASE.topic, ROBOT_COMMAND.topic)


class Replayer:
    """Re-publishes a share of what it sees, at once and ``late_s`` later."""

    def __init__(self, session, run_id: str, share: float, late_s: float, seed: int):
        self.rng = random.Random(seed)
        self.share, self.late_s = share, late_s
        self.pubs = {t: session.declare_publisher(topics.key(run_id, t)) for t in TOPICS}
        self.subs = [session.declare_subscriber(topics.key(run_id, t), self._on(t)) for t in TOPICS]
        self.replayed = {t: 0 for t in TOPICS}
        self._later: list = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._late_loop, daemon=True)
        self._thread.start()

    def _on(self, topic):
        def callback(sample):
            if self.rng.random() >= self.share:
                return
            raw = sample.payload.to_bytes()
            self.pubs[topic].put(raw)
            with self._lock:
                heapq.heappush(self._later, (time.monotonic() + self.late_s, id(raw), topic, raw))
                self.replayed[topic] += 2
        return callback

    def _late_loop(self):
        while not self._stop.wait(0.001):
            now = time.monotonic()
            with self._lock:
                due = []
                while self._later and self._later[0][0] <= now:
                    due.append(heapq.heappop(self._later))
            for _, _, topic, raw in due:
                self.pubs[topic].put(raw)

    def close(self):
        self._stop.set()
        self._thread.join(1)
        for s in self.subs:
            s.undeclare()


class Forger:
    """Publishes, every ``every_s``, a robot/command far ahead of its last one and garbage,
    each twice; ``rounds``: how many times."""

    STEP = 997  # cycles past the forger's last: soon far past the run's own

    def __init__(self, session, run_id: str, every_s: float = 0.3, measurements: bool = False):
        import numpy as np

        self.command = session.declare_publisher(topics.key(run_id, ROBOT_COMMAND.topic))
        self.wrench = session.declare_publisher(topics.key(run_id, FT_WRENCH.topic))
        self.measurements = measurements
        if measurements:  # (a declared publisher is a route Zenoh keeps: none the forger does not use)
            self.state = session.declare_publisher(topics.key(run_id, ROBOT_STATE.topic))
            self.contact = session.declare_publisher(topics.key(run_id, ROBOT_CONTACT.topic))
        self.pose = np.eye(3, 4).reshape(12)
        self.every_s, self.rounds = every_s, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self):
        seq = 1
        while not self._stop.wait(self.every_s):
            forged = ROBOT_COMMAND.encode(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=1, cart_pos=self.pose,
                                          cart_stiffness=[1000.0] * 6, cart_damping=[0.7] * 6, add_tcp_ft=[0.0] * 6,
                                          requested_mode=7, phase=0, estimate_seq=-1, goal_reached=True, hold="",
                                          episode=0)
            measured = self._measurements(seq) if self.measurements else ()
            for _ in range(2):
                for publisher, payload in measured:
                    publisher.put(payload)
                self.command.put(forged)
                self.command.put(b"\x00garbage{")
                self.wrench.put(b'{"seq": "x"}')
            self.rounds += 1
            seq += self.STEP

    def _measurements(self, seq: int) -> tuple:
        """A robot/state and a robot/contact of cycle ``seq``: the arm at rest in command mode, no contact."""
        state = ROBOT_STATE.encode(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=1, reflected_seq=-1, fri_state=2,
                                   fri_quality=3, control_mode=2, msr_jnt_pos=[0.0] * 7, msr_cart_pos=self.pose,
                                   est_ext_tcp_ft=[0.0] * 6, answer_rate=1.0, latency_s=0.0, jitter_s=0.0,
                                   miss_rate=0.0, safety=0, gravity_compensation=False, episode=0)
        contact = ROBOT_CONTACT.encode(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=1, wrench=[0.0] * 6,
                                       contact_force=[0.0] * 3, touching=[], true_phase=0, tcp_pose=self.pose,
                                       tcp_twist=[0.0] * 6, episode=0)
        return (self.state, state), (self.contact, contact)

    def close(self):
        self._stop.set()
        self._thread.join(1)


def one_run(label: str, out: Path, share: float, late_s: float, seed: int,
            forge: bool = False, measurements: bool = False) -> tuple[dict, dict, int]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run_id = f"replay-{label}-{int(time.time() * 1000)}"
    peer = open_session(ZenohOptions(listen=(endpoint,)))
    replayer = Replayer(peer, run_id, share, late_s, seed) if share > 0 else None
    forger = Forger(peer, run_id, measurements=measurements) if forge else None
    try:
        report = run(load_scenario(ROOT / "scenarios" / "smoke.yaml"),
                     RunOptions(out=str(out / label), run_id=run_id, zenoh=ZenohOptions(connect=(endpoint,))),
                     progress=lambda m: print(f"[{label}] {m}", file=sys.stderr))
    finally:
        if replayer is not None:
            replayer.close()
        if forger is not None:
            forger.close()
        peer.close()
    return report, (replayer.replayed if replayer else {t: 0 for t in TOPICS}), (forger.rounds if forger else 0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--share", type=float, default=0.1, help="share of the messages re-published (default 0.1)")
    p.add_argument("--late-ms", type=float, default=30.0, help="delay of the stale copy, ms (default 30)")
    p.add_argument("--seed", type=int, default=0, help="seed of which messages are re-published")
    p.add_argument("--forge", action="store_true",
                   help="also forge robot/commands far ahead (mode 7, sent_ns 1) and garbage, every 0.3 s")
    p.add_argument("--forge-measurements", action="store_true",
                   help="with --forge: also forge robot/state and robot/contact with the forged commands' seq")
    args = p.parse_args(argv)
    if args.forge_measurements and not args.forge:
        p.error("--forge-measurements goes with --forge")
    out = Path(tempfile.mkdtemp(prefix="replay_"))
    clean, _, _ = one_run("clean", out, 0.0, 0.0, args.seed)
    dirty, replayed, forged = one_run("replayed", out, args.share, args.late_ms / 1e3, args.seed, args.forge,
                                       args.forge_measurements)
    print(f"smoke scenario, lockstep over Zenoh; a foreign peer re-published {args.share:.0%} of the messages on "
          f"{', '.join(TOPICS)}, each at once and {args.late_ms:g} ms later")
    print("replayed copies: " + ", ".join(f"{t} {n}" for t, n in replayed.items()))
    if args.forge:
        print(f"forged: {forged} rounds, each twice: a robot/command {Forger.STEP} cycles past the last (mode 7, "
              "sent_ns 1), garbage on robot/command and ft/wrench"
              + (", a robot/state and a robot/contact of the command's seq" if args.forge_measurements else ""))
        forged_topics = (ROBOT_COMMAND.topic, FT_WRENCH.topic,
                         *((ROBOT_STATE.topic, ROBOT_CONTACT.topic) if args.forge_measurements else ()))
        judged = {k: {n: v.get(n, 0) for n in ("bad", "ahead", "resyncs", "off_clock")}
                  for k, v in dirty["timing"]["links_received"].items() if k.startswith(forged_topics)}
        print("judged by the receivers: " + "; ".join(f"{k}: {v}" for k, v in sorted(judged.items())))
    dropped = {k: v.get("dropped", 0) for k, v in dirty["timing"]["links_received"].items() if v.get("dropped")}
    print("dropped by the receivers (duplicates, older than the newest, past the robot's measurement): "
          + (", ".join(f"{k} {v}" for k, v in sorted(dropped.items())) or "none"))
    print(f"{'':28}{'clean':>22}{'replayed':>22}")
    rows = [("error", lambda r: str(r["error"])), ("phases chosen", lambda r: r["summary"]["phases_chosen"]),
            ("successes", lambda r: r["summary"]["successes"]),
            ("online phase accuracy", lambda r: r["summary"]["online_phase_accuracy"])]

    def repro(i, get):
        # a failed run may have fewer reproductions: None where it has none
        return lambda r: get(r["reproductions"][i]) if i < len(r["reproductions"]) else None

    for i in range(max(len(clean["reproductions"]), len(dirty["reproductions"]))):
        rows += [(f"repro {i} peak force [N]", repro(i, lambda e: e["peak_contact_force"])),
                 (f"repro {i} FRI late", repro(i, lambda e: e["fri"]["late"])),
                 (f"repro {i} FRI missed", repro(i, lambda e: e["fri"]["missed"])),
                 (f"repro {i} final x [m]", repro(i, lambda e: e["final_position"][0]))]
    same = True
    for name, get in rows:
        a, b = get(clean), get(dirty)
        same &= a == b
        print(f"{name:28}{str(a):>22}{str(b):>22}")
    print("results identical: " + ("yes" if same else "NO"))
    failed = [f"the {name} run failed" for name, r in (("clean", clean), ("replayed", dirty)) if r["error"] is not None]
    if args.forge:
        # the defence shown, not only an unchanged result: forgeries were sent and the robot dropped them
        ahead = dirty["timing"]["links_received"].get(f"{ROBOT_COMMAND.topic} -> robot", {}).get("ahead", 0)
        failed += [what for what, bad in (("no round of forgeries was sent", forged == 0),
                                          ("the robot dropped no command as ahead of it", ahead == 0)) if bad]
    for line in failed:
        print(f"NOT SHOWN: {line}")
    return 0 if same and not failed else 1


if __name__ == "__main__":
    sys.exit(main())
