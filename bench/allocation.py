"""What the 1 ms control step allocates, measured two ways.

The control step is what the cell runs between two FRI packets:

    sim.joint_positions(q); sim.joint_velocities(qd)
    tau = krc.compute(q, qd, command, hold=...)
    sim.apply(tau, hand_wrench); sim.step()

``traced_allocation`` uses tracemalloc, which sees Python objects, numpy array
data (numpy registers its allocator with it) and numba's runtime
(PyMem_RawMalloc), in-process.  It does not see C and C++ heap blocks (eigenpy,
Pinocchio, MuJoCo): ``count_mallocs`` sees every one of them by running the
steps in a child process with a malloc counter preloaded (LD_PRELOAD, compiled
here with the system's C compiler) and PYTHONMALLOC=malloc, so Python's own
objects go through it too.

    python bench/allocation.py [--steps 2000]

prints both for the control step of every KRC mode (``control_steps``).
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
import tracemalloc
from collections.abc import Callable

import numpy as np
import pinocchio as pin

from robot_sim.arm.kinematics import ArmKinematics, READY
from robot_sim.krc.law import ImpedanceCommand, KrcController, POSITION, SafetyReason, pose_to_cart_pos
from robot_sim.world.physics import Simulation
from robot_sim.world.teacher import DOWN
from robot_sim.world.tasks import Valley, free_space, valley

WARM_UP = 300  # covers numba's first calls and several Lambda refreshes
HAND = np.array([0.0, 1.5, -0.5, 0.05, 0.0, 0.02])  # a light touch: the hand path of apply() runs too

Step = Callable[[], None]


def control_step(sim: Simulation, krc: KrcController, command: ImpedanceCommand | None = None, *, hold: bool = True,
                 hand: np.ndarray | None = None, external_force: np.ndarray | None = None) -> Step:
    """The control step as a closure over its own q and qd buffers."""
    q, qd = np.empty(7), np.empty(7)

    def step():
        sim.joint_positions(q)
        sim.joint_velocities(qd)
        tau = krc.compute(q, qd, command, hold=hold, external_force=external_force)
        sim.apply(tau, hand)
        sim.step()

    return step


def _arm(world=None):
    kin = ArmKinematics()
    sim = Simulation(world or free_space())
    sim.reset(READY)
    return sim, kin, KrcController(kin)


def _cart_imp():
    sim, kin, krc = _arm()
    x0 = kin.forward(READY)
    target = pin.SE3(pin.exp3(np.array([0.0, 0.1, 0.2])) @ x0.rotation, x0.translation + [0.05, -0.04, 0.03])
    cmd = ImpedanceCommand(pose_to_cart_pos(target), np.array([2000.0] * 3 + [150.0] * 3), np.full(6, 0.7),
                           np.array([1.0, 0.0, -2.0, 0.0, 0.1, 0.0]))
    # the cell passes the force estimate every cycle
    return control_step(sim, krc, cmd, hold=False, hand=HAND, external_force=np.array([0.0, 0.5, 1.0])), krc


def _cart_imp_on_plate():
    g = Valley()
    sim, kin, krc = _arm(valley(g))
    n = g.plate_normal(-1)
    y = -0.08
    contact = np.array([0.6, y, g.surface_z(y)]) + n * kin.description.tool.tip_radius
    sim.reset(kin.inverse_kinematics(pin.SE3(DOWN, contact + 0.002 * n), READY))
    cmd = ImpedanceCommand(pose_to_cart_pos(pin.SE3(DOWN, contact - 0.01 * n)), np.array([1000.0] * 3 + [150.0] * 3),
                           np.full(6, 0.7), np.zeros(6))
    return control_step(sim, krc, cmd, hold=False), krc


def _cartesian_hold():
    sim, _, krc = _arm()
    return control_step(sim, krc, hand=HAND), krc


def _gravity_compensation():
    sim, _, krc = _arm()
    krc.gravity_compensation = True
    return control_step(sim, krc, hand=HAND), krc


def _position():
    sim, _, krc = _arm()
    krc.switch_mode(POSITION)
    krc.set_joint_target(READY + np.array([0.2, -0.1, 0.1, 0.15, -0.2, 0.1, 0.3]))
    return control_step(sim, krc, hand=HAND), krc


def _joint_hold():
    sim, _, krc = _arm()
    krc.compute(sim.joint_positions(), np.zeros(7), external_force=np.array([0.0, 0.0, 1e3]))  # over the limit
    if krc.safety != SafetyReason.CARTESIAN_FORCE:
        raise RuntimeError(f"expected a Cartesian force stop, the KRC reports {krc.safety}")
    return control_step(sim, krc, hand=HAND), krc


# the KRC's modes, each with the safety state it must still be in after the steps
CONTROL_STEPS = {
    "cart_imp": (_cart_imp, SafetyReason.NONE),
    "cart_imp_on_plate": (_cart_imp_on_plate, SafetyReason.NONE),
    "cartesian_hold": (_cartesian_hold, SafetyReason.NONE),
    "gravity_compensation": (_gravity_compensation, SafetyReason.NONE),
    "position": (_position, SafetyReason.NONE),
    "joint_hold": (_joint_hold, SafetyReason.CARTESIAN_FORCE),
}


def control_steps() -> dict[str, tuple[Step, KrcController]]:
    """{mode: (step, its KRC)}: a fresh arm for the control step of every KRC mode."""
    return {name: make() for name, (make, _) in CONTROL_STEPS.items()}


def traced_allocation(step: Step, steps: int, warm_up: int = WARM_UP) -> tuple[int, int]:
    """(net growth of traced memory over ``steps`` steps, largest transient of one step), bytes.

    The bookkeeping allocates nothing while tracing: the readings go into
    arrays, and the loop's iterator and ints exist before tracing starts.
    tracemalloc sees every thread, so a caller that needs zero should take the
    best of a few runs."""
    for _ in range(warm_up):
        step()
    current = np.zeros(steps + 1, dtype=np.int64)
    peak = np.zeros(steps, dtype=np.int64)
    indices = iter(list(range(steps)))
    tracemalloc.start()
    try:
        for i in indices:
            current[i] = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            step()
            peak[i] = tracemalloc.get_traced_memory()[1]
        current[steps] = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    return int(current[steps] - current[0]), int((peak - current[:steps]).max())


# ------------------------------------------------------------ C-level count

MALLOC_COUNTER_SOURCE = r"""
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

_COUNTER_ENV = "ROBOT_SIM_MALLOC_COUNTER"


class MallocCountUnavailable(RuntimeError):
    """No C compiler, or the child process failed; the message says which."""


def _child_counts(steps: int, modes: list[str]) -> dict[str, list[int]]:
    """In the child: {mode: [[mallocs, bytes] over 0 steps, [mallocs, bytes] over ``steps`` steps]}, best of 3 runs."""
    lib = ctypes.CDLL(os.environ[_COUNTER_ENV])
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
    for name in modes:
        step, _ = CONTROL_STEPS[name][0]()
        for _ in range(WARM_UP):
            step()
        # the counter's own ctypes calls cost the same with 0 steps as with n;
        # another thread (numba's, Zenoh's are not here) may allocate in one run
        overhead = min(count(step, 0) for _ in range(3))
        out[name] = [overhead, min(count(step, steps) for _ in range(3))]
    return out


def count_mallocs(steps: int = 2000, modes: list[str] | None = None) -> dict[str, tuple[int, int]]:
    """{mode: (C-level allocations over ``steps`` control steps, their bytes)}, the
    counter's own overhead taken off; raises MallocCountUnavailable when it cannot count."""
    modes = list(CONTROL_STEPS) if modes is None else modes
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise MallocCountUnavailable("no C compiler (cc, gcc) on PATH to build the malloc counter")
    with tempfile.TemporaryDirectory() as tmp:
        src, lib = os.path.join(tmp, "malloc_counter.c"), os.path.join(tmp, "libmalloc_counter.so")
        with open(src, "w") as f:
            f.write(MALLOC_COUNTER_SOURCE)
        built = subprocess.run([cc, "-O2", "-shared", "-fPIC", "-o", lib, src], check=False, capture_output=True,
                               text=True)
        if built.returncode != 0:
            raise MallocCountUnavailable(f"{cc} failed on the malloc counter: {built.stderr.strip()}")
        env = dict(os.environ, LD_PRELOAD=lib, PYTHONMALLOC="malloc", **{_COUNTER_ENV: lib})
        child = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", "--steps", str(steps),
                                "--modes", ",".join(modes)], check=False, env=env, capture_output=True,
                               text=True)
    if child.returncode != 0:
        tail = child.stderr.strip().splitlines()[-1:] or [f"exit {child.returncode}"]
        raise MallocCountUnavailable(f"the counting child failed: {tail[0]}")
    counts = json.loads(child.stdout.strip().splitlines()[-1])
    return {name: (calls - calls0, nbytes - nbytes0) for name, ((calls0, nbytes0), (calls, nbytes)) in counts.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python bench/allocation.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=2000, help="control steps per mode (default 2000)")
    parser.add_argument("--modes", default=",".join(CONTROL_STEPS), help="comma-separated KRC modes")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    modes = [m for m in args.modes.split(",") if m]
    unknown = sorted(set(modes) - set(CONTROL_STEPS))
    if unknown:
        parser.error(f"--modes: unknown {unknown}; known: {', '.join(CONTROL_STEPS)}")
    if args.child:
        print(json.dumps(_child_counts(args.steps, modes)))
        return 0
    try:
        mallocs, why = count_mallocs(args.steps, modes), None
    except MallocCountUnavailable as e:
        mallocs, why = {}, str(e)
    print(f"{'KRC mode':<22} {'traced growth B':>16} {'traced peak B':>14} {'C mallocs':>10} {'C bytes':>9}"
          f"   over {args.steps} steps")
    for name in modes:
        step, _ = CONTROL_STEPS[name][0]()
        growth, peak = min(traced_allocation(step, args.steps) for _ in range(3))
        calls, nbytes = mallocs.get(name, ("-", "-"))
        print(f"{name:<22} {growth:>16} {peak:>14} {calls:>10} {nbytes:>9}")
    if why:
        print(f"C mallocs not counted: {why}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
