"""What an in-process engine without a Python call per node per message could reach: the
pieces of the two designs measured side by side, before one is built.

    python bench/engine_prototypes.py [--cycles 5000] [--episodes 1,4,16] [--out DIR]

In one process, one after the other, on the valley's cell with the tool pressed on a plate
(``bench/sim_step.py``), each figure the best of three:

- **floor**: the bare loop of the physics, the KRC's law and MuJoCo's step, from Python
  (what ``bench/lockstep_rtf.py`` divides by);
- **the cell's cycle**: the whole cell as the robot node steps it (the FRI link's
  measurement and command in Python, the law, the step, the ATI sample), no node and no bus;
- **the per-message engine**: a smoke run in one process (its seed, no figures), the
  reproduction's wall time per cycle: every node's handlers, the bus, the recorder;
- **a reproduction cycle in Python glue** (fused cycles with Python between the compiled
  pieces): one loop, no bus: the cell's kernels and the FRI link's books, the ATI sample,
  the commander's compiled policy, the command through the link's checks, the four
  messages packed with orjson straight from the arrays and handed to the recorder's writer
  process (a prototype: none of the nodes' other logic);
- **encoding a cycle's messages**: robot/state, robot/contact, ft/wrench and robot/command
  packed from their fields (``MessageType.pack``, the bytes recorded), from the smoke
  reproduction's own messages: what any engine that records the same bytes pays;
- **MuJoCo's step from a compiled loop**: ``mj_step`` called through its C symbol from a
  numba kernel, ten 1 ms cycles per call, against the same steps from Python, and whether
  both leave the same state bit for bit (fused cycles need the step inside the kernel);
- **episodes side by side** (batched episodes): N cells, each its own MjData, stepped one
  cycle each in turn from Python: the cost of a cycle per episode as N grows (what
  batching can save is what is paid once per cycle for all N; MuJoCo's step itself is per
  model and data).

Prints microseconds per 1 ms cycle and each as a multiple of the floor.
"""

from __future__ import annotations

import argparse
import ctypes
import glob
import itertools
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))


def best(fn, repeats=3):
    return min(fn() for _ in range(repeats))


def per_message_engine(out: Path) -> tuple[float, Path]:
    """us per cycle of the smoke's reproduction in one process, and its recording."""
    from services.run.options import RunOptions
    from services.run.runner import run
    from services.scenario import load_scenario

    report = run(load_scenario(str(ROOT / "scenarios" / "smoke.yaml")),
                 RunOptions(out=str(out), run_id="prototypes", transport="inproc", figures=False),
                 progress=lambda line: None)
    if report["error"]:
        raise SystemExit(f"the smoke run failed: {report['error']}")
    (rep,) = report["reproductions"]
    cycles = report["timing"]["robot_loop"]["per_episode"][-1]["cycles"]
    return rep["wall_seconds"] / cycles * 1e6, out / "recordings" / "reproduction_00.mcap"


def encoding_us(recording: Path) -> float:
    """us to pack one cycle's four 1 kHz messages from their fields, over the recording."""
    from services.recordings.reader import read_episode
    from services.runtime.messages import FT_WRENCH, ROBOT_COMMAND, ROBOT_CONTACT, ROBOT_STATE

    types = {t.channel: t for t in (ROBOT_STATE, ROBOT_CONTACT, FT_WRENCH, ROBOT_COMMAND)}
    fields = [(types[m.topic], types[m.topic].decode(m.payload))
              for m in read_episode(recording).messages if m.topic in types]
    cycles = len(fields) / len(types)

    def once():
        t = time.perf_counter()
        for mtype, values in fields:
            mtype.pack(**values)
        return (time.perf_counter() - t) / cycles * 1e6
    return best(once)


def compiled_steps(cycles: int) -> tuple[float, float, bool]:
    """(us per step from a numba loop, us per step from Python, same state bit for bit)."""
    import mujoco
    from numba import njit

    from sim_step import pressed_cell

    library = glob.glob(os.path.join(os.path.dirname(mujoco.__file__), "libmujoco.so*"))[0]
    mj_step = ctypes.CDLL(library).mj_step
    mj_step.argtypes, mj_step.restype = [ctypes.c_void_p, ctypes.c_void_p], None

    @njit
    def ten_cycles(model, data, n):
        for _ in range(n):
            mj_step(model, data)

    cell, q0, _, _ = pressed_cell()
    model = cell.sim.model
    a, b = mujoco.MjData(model), mujoco.MjData(model)
    for d in (a, b):
        d.qpos[:7] = q0
        d.qfrc_applied[:7] = 0.0
        mujoco.mj_forward(model, d)
    ten_cycles(model._address, a._address, 1)
    mujoco.mj_step(model, b)

    def from_numba():
        t = time.perf_counter()
        for _ in range(cycles // 10):
            ten_cycles(model._address, a._address, 10)
        return (time.perf_counter() - t) / (cycles // 10 * 10) * 1e6

    def from_python():
        t = time.perf_counter()
        for _ in range(cycles // 10 * 10):
            mujoco.mj_step(model, b)
        return (time.perf_counter() - t) / (cycles // 10 * 10) * 1e6
    numba_us, python_us = best(from_numba), best(from_python)
    same = bool(np.array_equal(a.qpos, b.qpos) and np.array_equal(a.qvel, b.qvel))
    return numba_us, python_us, same


def side_by_side(n: int, cycles: int) -> float:
    """us per cycle per episode, n cells stepped one cycle each in turn (law and physics)."""
    from sim_step import law_and_physics, pressed_cell

    loops = []
    for _ in range(n):
        cell, q0, cmd, _ = pressed_cell()
        cell.place(q0)
        loops.append(law_and_physics(cell, cmd))
    rounds = max(1, cycles // n)

    def once():
        t = time.perf_counter()
        for _ in range(rounds):
            for step in loops:
                step(1)
        return (time.perf_counter() - t) / (rounds * n) * 1e6
    return best(once)


def python_glue_cycle(cycles: int, out: Path) -> float:
    """us per cycle of a reproduction stepped by one Python loop with no bus: what fused cycles
    with Python glue between the compiled pieces would cost.  Each cycle: the cell's
    measurement (its kernel and the FRI link's books), the ATI sample, the commander's
    compiled policy on the smoke's learned task, its command through the link's checks, the
    cell's physics cycle, and the four 1 kHz messages packed with orjson straight from the
    arrays (``OPT_SERIALIZE_NUMPY``: the same bytes as from lists) and handed to the
    recorder's writer process, which writes the MCAP file on the other CPU, as in a run in
    one process.  A prototype: not the nodes' logic (no estimator, holds, judge or labels), so its
    recording is not the per-message engine's; it says what the loop itself costs."""
    import orjson

    from etar.policy import ReproductionPolicy
    from etar.policy_kernel import compiled_policy
    from etar.task import load_task
    from robot_sim.ati.sensor import AtiConfig, AtiSensor
    from robot_sim.krc.packets import CommandPacket, ControlMode
    from services.recordings.offload import WriterProcess
    from services.runtime.messages import FT_WRENCH, ROBOT_COMMAND, ROBOT_CONTACT, ROBOT_STATE
    from sim_step import pressed_cell

    numpy_option = orjson.OPT_SERIALIZE_NUMPY
    task = load_task(str(ROOT / "scenarios" / "models" / "smoke.json"))
    cell, q0, _, _ = pressed_cell()
    cell.ati = None  # sampled below, as the ft_sensor node samples it (the robot's cell has no sensor)
    cell.start()
    cell.place(q0)
    cell.fri.request_command_mode()
    ati = AtiSensor(AtiConfig.mini45(), 0, clock_origin_ns=0)
    stiffness, damping = np.array([0.0] * 3 + [150.0] * 3), np.full(6, 0.7)
    cart, add = np.empty((3, 4)), np.zeros(6)
    keys = {t: f"etar/prototype/{t.topic}" for t in (ROBOT_STATE, ROBOT_CONTACT, FT_WRENCH, ROBOT_COMMAND)}

    def loop(k: int, writer, policy) -> float:
        t = time.perf_counter()
        for _ in range(k):
            m = cell.begin_cycle()
            seq, stamp = m.seq, m.stamp_ns
            state = orjson.dumps({
                "seq": seq, "stamp_ns": stamp, "sent_ns": 0, "reflected_seq": m.reflected_seq,
                "fri_state": int(m.state), "fri_quality": int(m.quality), "control_mode": int(m.control_mode),
                "msr_jnt_pos": m.msr_jnt_pos, "msr_cart_pos": m.msr_cart_pos, "est_ext_tcp_ft": m.est_ext_tcp_ft,
                "answer_rate": m.answer_rate, "latency_s": m.latency_s, "jitter_s": m.jitter_s,
                "miss_rate": m.miss_rate, "safety": 0, "gravity_compensation": False, "episode": 0},
                option=numpy_option)
            wrench = cell._true_wrench
            contact = orjson.dumps({
                "seq": seq, "stamp_ns": stamp, "sent_ns": 0, "wrench": wrench, "contact_force": cell._contact_force,
                "touching": cell._touching, "true_phase": 1, "tcp_pose": cell._true_pose.reshape(12),
                "tcp_twist": cell._true_twist, "episode": 0}, option=numpy_option)
            rec, w = ati.sample(wrench, stamp)
            ft = orjson.dumps({
                "seq": seq, "stamp_ns": stamp, "sent_ns": 0, "rdt_sequence": rec.rdt_sequence,
                "ft_sequence": rec.ft_sequence, "status": rec.status, "counts": rec.counts,
                "counts_per_force": 1e6, "counts_per_torque": 1e6, "wrench": w}, option=numpy_option)
            force, rotation, x = policy.tool_step(m.msr_cart_pos, m.est_ext_tcp_ft[:3], 1, 0.001)
            cart[:, :3], cart[:, 3], add[:3] = rotation, x, force
            packet = CommandPacket(seq, cart.reshape(12).copy(), stiffness, damping, add.copy(), None,
                                   ControlMode.CART_IMP)
            cell.deliver(packet, stamp + 100_000, owned=True)
            command = orjson.dumps({
                "seq": seq, "stamp_ns": stamp, "sent_ns": 0, "cart_pos": packet.cart_pos,
                "cart_stiffness": stiffness, "cart_damping": damping, "add_tcp_ft": packet.add_tcp_ft,
                "requested_mode": 2, "phase": 1, "estimate_seq": seq, "goal_reached": False, "hold": "",
                "episode": 0}, option=numpy_option)
            cell.end_cycle()
            for mtype, payload in ((ROBOT_STATE, state), (ROBOT_CONTACT, contact), (FT_WRENCH, ft),
                                   (ROBOT_COMMAND, command)):
                writer.add(keys[mtype], payload, stamp)
        return (time.perf_counter() - t) / k * 1e6

    process, runs = WriterProcess(), itertools.count(1)

    def once():
        index = next(runs)
        policy = compiled_policy(ReproductionPolicy(task.impedances, task.goal))
        writer = process.open(out / f"glue_{index}.mcap", run_id="prototype", episode_kind="reproduction",
                              episode_index=index)
        try:
            loop(600, writer, policy)  # command mode entered (500 PERFECT cycles), the arm pressing
            return loop(cycles, writer, policy)
        finally:
            writer.finish()
    try:
        return best(once)
    finally:
        process.close()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cycles", type=int, default=5000, help="cycles timed per figure (best of 3)")
    parser.add_argument("--episodes", default="1,4,16", help="numbers of episodes stepped side by side")
    parser.add_argument("--out", default=None, help="folder for the smoke run (default: a temporary one)")
    args = parser.parse_args(argv)
    try:
        counts = [int(n) for n in args.episodes.split(",")]
        if not counts or min(counts) < 1:
            raise ValueError
    except ValueError:
        parser.error(f"--episodes: comma-separated integers >= 1, got {args.episodes!r}")

    from sim_step import physical_floor_us, whole_cell_cycle

    floor = best(lambda: physical_floor_us(args.cycles))
    cell_cycle = best(lambda: whole_cell_cycle(args.cycles)[0])
    with tempfile.TemporaryDirectory() as tmp:
        engine, recording = per_message_engine(Path(args.out or tmp) / "smoke")
        encode = encoding_us(recording)
        glue = python_glue_cycle(args.cycles, Path(tmp))
    numba_step, python_step, same = compiled_steps(args.cycles)
    batched = {n: side_by_side(n, args.cycles) for n in counts}

    rows = [("floor: the KRC's law and MuJoCo's step, from Python", floor),
            ("the cell's whole cycle (FRI link, law, step, ATI), no nodes", cell_cycle),
            ("the per-message engine, smoke reproduction", engine),
            ("a reproduction cycle in Python glue, no bus (prototype)", glue),
            ("packing one cycle's four 1 kHz messages", encode),
            ("MuJoCo's step alone, from Python", python_step),
            ("MuJoCo's step alone, from a numba loop (10 cycles a call)", numba_step)]
    rows += [(f"law and step, {n} episode(s) side by side, per episode", us) for n, us in batched.items()]
    width = max(len(r[0]) for r in rows)
    for name, us in rows:
        print(f"{name:<{width}}  {us:7.1f} us  {us / floor:5.1f}x the floor")
    print(f"MuJoCo's step from numba leaves the state Python's leaves, bit for bit: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
