"""MCAP recorder throughput: messages per second through ``EpisodeWriter``, without and
with Foxglove's visual topics.

    python bench/recorder_throughput.py [--seconds 30] [--visual-rate-hz 50]

Writes the message mix of a reproduction (robot_state, robot_contact,
ft_wrench, robot_command every cycle, estimator_phase every tenth) for the
given simulated time and reports messages/s, MB/s in and on disk, and the
headroom over the 4.1 kHz the services produce.  Then again as the recorder
does with its visual topics on: every payload through ``services.foxglove.tap.VisualTap``
and its visual messages written beside; what they cost in time per simulated
second (the recorder's CPU) and in file size.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from services.recordings.writer import EpisodeWriter
from services.recordings.reader import read_episode
from services.runtime.messages import ESTIMATOR_PHASE, FT_WRENCH, ROBOT_COMMAND, ROBOT_CONTACT, ROBOT_STATE


def payloads(cycles):
    rng = np.random.default_rng(0)
    out = []
    for k in range(cycles):
        h = dict(seq=k, stamp_ns=k * 1_000_000, sent_ns=k)
        out.append((ROBOT_STATE.topic, ROBOT_STATE.encode(
            **h, reflected_seq=k, fri_state=2, fri_quality=3, control_mode=2, msr_jnt_pos=rng.normal(size=7),
            msr_cart_pos=rng.normal(size=12), est_ext_tcp_ft=rng.normal(size=6), answer_rate=1.0, latency_s=1e-4,
            jitter_s=1e-5, miss_rate=0.0, safety=0, gravity_compensation=False, episode=0)))
        out.append((ROBOT_CONTACT.topic, ROBOT_CONTACT.encode(**h, wrench=rng.normal(size=6), contact_force=rng.normal(
            size=3), touching=["plate_left"], true_phase=1, episode=0)))
        out.append((FT_WRENCH.topic, FT_WRENCH.encode(**h, rdt_sequence=k, ft_sequence=k, status=0,
                                                   counts=[int(x) for x in rng.integers(-10**6, 10**6, 6)],
                                                   counts_per_force=1e6, counts_per_torque=1e6,
                                                   wrench=rng.normal(size=6))))
        out.append((ROBOT_COMMAND.topic, ROBOT_COMMAND.encode(
            **h, cart_pos=rng.normal(size=12), cart_stiffness=np.zeros(6), cart_damping=np.full(6, 0.7),
            add_tcp_ft=rng.normal(size=6), requested_mode=2, phase=1, estimate_seq=k, goal_reached=False, hold="",
            episode=0)))
        if k % 10 == 0:
            out.append((ESTIMATOR_PHASE.topic, ESTIMATOR_PHASE.encode(**h, posterior=[0.1, 0.8, 0.1], phase=1,
                                                                  input_seq=k, ft_seq=k, episode=0)))
    return out


def write(msgs, tap=None) -> tuple[float, int, int, int]:
    """(seconds, bytes on disk, visual messages, messages read back) of one episode file."""
    from services.foxglove.tap import encode

    visual = 0
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "bench.mcap"
        t = time.perf_counter()
        with EpisodeWriter(path, run_id="bench", episode_kind="reproduction", episode_index=0) as w:
            for i, (topic, payload) in enumerate(msgs):
                w.add(f"etar/bench/{topic}", payload, i)
                if tap is not None:
                    for visual_topic, message in tap.take(topic, payload):
                        w.add(visual_topic, encode(message), i, i)
                        visual += 1
        dt = time.perf_counter() - t
        size = path.stat().st_size
        n_read = len(read_episode(path).messages)
    return dt, size, visual, n_read


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=30.0, help="simulated seconds of traffic")
    parser.add_argument("--visual-rate-hz", type=float, default=50.0, help="the visual topics' rate, Hz (default 50)")
    args = parser.parse_args()
    from services.foxglove.scene import VisualScene
    from services.foxglove.tap import VisualTap

    msgs = payloads(int(args.seconds * 1000))
    raw = sum(len(p) for _, p in msgs)
    dt, size, _, n_read = write(msgs)
    rate = len(msgs) / dt
    produced = len(msgs) / args.seconds
    print(f"{len(msgs)} messages ({raw / 1e6:.1f} MB JSON) = {args.seconds:.0f} s of a reproduction's traffic")
    print(f"write: {dt:.2f} s, {rate:,.0f} messages/s, {raw / dt / 1e6:.1f} MB/s in, {size / 1e6:.2f} MB on disk "
          f"(zstd {raw / size:.1f}x); {rate / produced:.1f}x the {produced:,.0f} messages/s the services produce")
    print(f"read back: {n_read} messages")
    tap = VisualTap(VisualScene("valley", args.visual_rate_hz))
    dt_v, size_v, visual, n_read_v = write(msgs, tap)
    print(f"with the visual topics at {args.visual_rate_hz:g} Hz: {visual} visual messages, write {dt_v:.2f} s "
          f"({(dt_v - dt) / args.seconds * 1e3:.1f} ms more per simulated second = "
          f"{(dt_v - dt) / args.seconds * 100:.1f} % of one CPU), {size_v / 1e6:.2f} MB on disk "
          f"(+{(size_v - size) / size * 100:.0f} %, {(size_v - size) / args.seconds / 1e3:.0f} kB per simulated "
          f"second); {len(msgs) / dt_v:,.0f} messages/s = {len(msgs) / dt_v / produced:.1f}x what the services "
          f"produce; read back {n_read_v}")


if __name__ == "__main__":
    main()
