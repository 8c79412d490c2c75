"""Cost of one simulated FRI cycle (1 ms of physics) on this machine.

    python bench/sim_step.py [--cycles 5000] [--no-malloc-count]

Times, per 1 ms step: MuJoCo alone; MuJoCo + the KRC's Cartesian impedance law
(Pinocchio); and the whole cell cycle (FRI link bookkeeping, impedance law,
physics, ATI sensor), arm pressed against a valley plate (one contact).
Target (issue 3): under 100 us per step with the impedance law, i.e. the
simulation runs at least 10x faster than real time.

Then the control step alone (read q, qd; krc.compute; apply; step) in each of
the KRC's modes: us per step, what tracemalloc sees allocated per step (net
growth, and the largest transient of a single step), and C-level allocations
per step: a malloc counter compiled here with gcc is preloaded into a child
process run with PYTHONMALLOC=malloc, so that Python objects, numpy arrays,
numba's runtime and C++ (Pinocchio, eigenpy, MuJoCo) all go through it.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import tracemalloc

import numpy as np
import pinocchio as pin

from robot_sim.cell import RobotCell
from robot_sim.fri import CommandPacket
from robot_sim.kinematics import READY, ArmKinematics
from robot_sim.krc import (
    POSITION,
    ImpedanceCommand,
    KrcController,
    SafetyReason,
    pose_to_cart_pos,
)
from robot_sim.physics import Simulation
from robot_sim.teacher import DOWN
from robot_sim.worlds import Valley, free_space, valley

MALLOC_COUNTER = r"""
#include <stddef.h>
#include <stdatomic.h>
extern void *__libc_malloc(size_t);
extern void *__libc_calloc(size_t, size_t);
extern void *__libc_realloc(void *, size_t);
extern void *__libc_memalign(size_t, size_t);
extern void __libc_free(void *);
static atomic_int on;
static atomic_long calls, bytes;
static void note(size_t n) {
    if (atomic_load_explicit(&on, memory_order_relaxed)) {
        atomic_fetch_add(&calls, 1);
        atomic_fetch_add(&bytes, (long)n);
    }
}
void *malloc(size_t n) { note(n); return __libc_malloc(n); }
void *calloc(size_t k, size_t n) { note(k * n); return __libc_calloc(k, n); }
void *realloc(void *p, size_t n) { note(n); return __libc_realloc(p, n); }
void free(void *p) { __libc_free(p); }
void *memalign(size_t a, size_t n) { note(n); return __libc_memalign(a, n); }
void *aligned_alloc(size_t a, size_t n) { note(n); return __libc_memalign(a, n); }
int posix_memalign(void **r, size_t a, size_t n) {
    note(n);
    void *p = __libc_memalign(a, n);
    if (!p) return 12; /* ENOMEM */
    *r = p;
    return 0;
}
void malloc_counter_start(void) { atomic_store(&calls, 0); atomic_store(&bytes, 0); atomic_store(&on, 1); }
void malloc_counter_stop(long *c, long *b) { atomic_store(&on, 0); *c = atomic_load(&calls); *b = atomic_load(&bytes); }
"""


def per_step(fn, cycles):
    fn(200)  # warm up
    t = time.perf_counter()
    fn(cycles)
    return (time.perf_counter() - t) / cycles * 1e6


# ------------------------------------------------------------ control step


def control_steps():
    """{mode: step()} with the control step of each KRC mode, a light hand on the arm."""
    hand = np.array([0.0, 1.5, -0.5, 0.05, 0.0, 0.02])

    def arm(world=None):
        kin = ArmKinematics()
        sim = Simulation(world or free_space())
        sim.reset(READY)
        return sim, kin, KrcController(kin)

    def stepper(sim, krc, command=None, hold=True, hand=hand, external_force=None):
        q, qd = np.empty(7), np.empty(7)

        def step():
            sim.joint_positions(q)
            sim.joint_velocities(qd)
            tau = krc.compute(q, qd, command, hold=hold, external_force=external_force)
            sim.apply(tau, hand)
            sim.step()

        return step

    steps = {}
    g = Valley()
    sim, kin, krc = arm(valley(g))
    n = g.plate_normal(-1)
    contact = np.array([0.6, -0.08, g.surface_z(-0.08)]) + n * kin.description.tool.tip_radius
    sim.reset(kin.inverse_kinematics(pin.SE3(DOWN, contact + 0.002 * n), READY))
    cmd = ImpedanceCommand(pose_to_cart_pos(pin.SE3(DOWN, contact - 0.01 * n)), np.array([1000.0] * 3 + [150.0] * 3),
                           np.full(6, 0.7), np.zeros(6))
    steps["CART_IMP, on the plate"] = stepper(sim, krc, cmd, hold=False, hand=None, external_force=np.zeros(3))
    sim, kin, krc = arm()
    steps["cartesian hold"] = stepper(sim, krc)
    sim, kin, krc = arm()
    krc.gravity_compensation = True
    steps["gravity compensation"] = stepper(sim, krc)
    sim, kin, krc = arm()
    krc.switch_mode(POSITION)
    krc.set_joint_target(READY + np.array([0.2, -0.1, 0.1, 0.15, -0.2, 0.1, 0.3]))
    steps["POSITION"] = stepper(sim, krc)
    sim, kin, krc = arm()
    krc.compute(sim.joint_positions(), np.zeros(7), external_force=np.array([0.0, 0.0, 1e3]))
    assert krc.safety == SafetyReason.CARTESIAN_FORCE
    steps["safety joint hold"] = stepper(sim, krc)
    return steps


def traced(step, cycles):
    """(net traced bytes per step, largest traced transient of one step); the
    bookkeeping allocates nothing while tracing (buffers, iterator made before)."""
    for _ in range(300):
        step()
    current = np.zeros(cycles + 1, dtype=np.int64)
    peak = np.zeros(cycles, dtype=np.int64)
    indices = iter(list(range(cycles)))
    tracemalloc.start()
    for i in indices:
        current[i] = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        step()
        peak[i] = tracemalloc.get_traced_memory()[1]
    current[cycles] = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    return (current[cycles] - current[0]) / cycles, int((peak - current[:cycles]).max())


def count_mallocs(cycles):
    """Child side: {mode: (mallocs per step, bytes per step)} under the preloaded counter."""
    lib = ctypes.CDLL(os.environ["SIM_STEP_MALLOC_COUNTER"])
    calls, size = ctypes.c_long(), ctypes.c_long()
    pcalls, psize = ctypes.byref(calls), ctypes.byref(size)

    def count(step, n):
        loop = iter([None] * n)
        lib.malloc_counter_start()
        for _ in loop:
            step()
        lib.malloc_counter_stop(pcalls, psize)
        return calls.value, size.value

    out = {}
    for name, step in control_steps().items():
        for _ in range(300):
            step()
        # the difference between 2n and n steps: the counter's own ctypes calls cancel
        c1, b1 = count(step, cycles)
        c2, b2 = count(step, 2 * cycles)
        out[name] = ((c2 - c1) / cycles, (b2 - b1) / cycles)
    return out


def malloc_counts(cycles):
    """Parent side: compile the counter, run the child; None when that is not possible."""
    gcc = shutil.which("gcc")
    if gcc is None:
        return None, "gcc not found"
    with tempfile.TemporaryDirectory() as tmp:
        src, lib = os.path.join(tmp, "malloc_counter.c"), os.path.join(tmp, "libmalloc_counter.so")
        with open(src, "w") as f:
            f.write(MALLOC_COUNTER)
        subprocess.run([gcc, "-O2", "-shared", "-fPIC", "-o", lib, src], check=True)
        env = dict(os.environ, LD_PRELOAD=lib, PYTHONMALLOC="malloc", SIM_STEP_MALLOC_COUNTER=lib)
        child = subprocess.run([sys.executable, __file__, "--malloc-child", "--cycles", str(cycles)], env=env,
                               capture_output=True, text=True, check=False)
    if child.returncode != 0:
        return None, child.stderr.strip().splitlines()[-1] if child.stderr.strip() else f"exit {child.returncode}"
    return json.loads(child.stdout.strip().splitlines()[-1]), None


# -------------------------------------------------------------------- main


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cycles", type=int, default=5000)
    parser.add_argument("--no-malloc-count", action="store_true", help="skip the C-level allocation count")
    parser.add_argument("--malloc-child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.malloc_child:
        print(json.dumps(count_mallocs(min(args.cycles, 2000))))
        return
    g = Valley()
    cell = RobotCell(valley(g), seed=0)
    n = g.plate_normal(-1)
    y = -0.08
    contact = np.array([0.6, y, g.surface_z(y)]) + n * cell.kin.description.tool.tip_radius
    q0 = cell.place_tcp(contact + 0.002 * n, DOWN)
    setpoint = pin.SE3(DOWN, contact - 0.01 * n)
    stiffness = np.array([1000.0] * 3 + [150.0] * 3)
    cmd = ImpedanceCommand(pose_to_cart_pos(setpoint), stiffness, np.full(6, 0.7), np.zeros(6))
    sim, krc = cell.sim, cell.krc
    q, qd = np.empty(7), np.empty(7)

    def physics_only(k):
        for _ in range(k):
            sim.apply(np.zeros(7))
            sim.step()

    def with_law(k):
        for _ in range(k):
            sim.joint_positions(q)
            sim.joint_velocities(qd)
            tau = krc.compute(q, qd, cmd, hold=False)
            sim.apply(tau)
            sim.step()

    cell.start()

    def whole_cycle(k):
        for _ in range(k):
            m = cell.begin_cycle()
            cell.receive(CommandPacket(m.seq, cmd.cart_pos, stiffness, np.full(6, 0.7)), m.stamp_ns + 100_000)
            cell.end_cycle()

    cell.place(q0)
    t_phys = per_step(physics_only, args.cycles)
    cell.place(q0)
    t_law = per_step(with_law, args.cycles)
    cell.place(q0)
    cell.fri.request_command_mode()
    whole_cycle(700)  # quality PERFECT for 500 cycles, then CMD: the arm presses on the plate
    assert cell.fri.state == 2, cell.fri.state
    t_cell = per_step(whole_cycle, args.cycles)
    touching = cell.sim.touching()
    print(f"{'what':<52} {'us/step':>8} {'x real time':>12}")
    for name, t in (("MuJoCo step alone (arm + contact)", t_phys),
                    ("+ KRC Cartesian impedance law (Pinocchio)", t_law),
                    ("whole cell cycle: FRI + law + physics + ATI", t_cell)):
        print(f"{name:<52} {t:>8.1f} {1000.0 / t:>12.1f}")
    print(f"contact during the run: {touching}; target: < 100 us per step with the law")

    cycles = min(args.cycles, 2000)
    counts, why = (None, "skipped") if args.no_malloc_count else malloc_counts(cycles)
    print(f"\ncontrol step (q, qd -> krc.compute -> apply -> step), {cycles} steps per mode")
    print(f"{'KRC mode':<26} {'us/step':>8} {'traced B/step':>14} {'peak B/step':>12} {'mallocs/step':>13} "
          f"{'malloc B/step':>14}")
    for name, step in control_steps().items():
        t = per_step(lambda k, step=step: [step() for _ in range(k)], cycles)
        growth, peak = traced(step, cycles)
        c, b = counts[name] if counts else (float("nan"), float("nan"))
        print(f"{name:<26} {t:>8.1f} {growth:>14.1f} {peak:>12d} {c:>13.2f} {b:>14.0f}")
    print("traced: tracemalloc (Python objects, numpy data, numba's runtime); peak: the largest transient of one "
          "step;\nmallocs: every C-level allocation in the process (PYTHONMALLOC=malloc, counter preloaded)"
          + (f" -- not measured: {why}" if counts is None else ""))


if __name__ == "__main__":
    main()
