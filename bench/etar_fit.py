"""EM and online-filter speed of the ETAR library.

    python bench/etar_fit.py [--repeats 3]

Fits 6 demonstrations x 3000 samples (n=3 state, m=3 force, K=3 phases) for
exactly 50 EM iterations (one initialisation, no early stop), times the
online filter's ``update``, then the fits a run's phase-count vote makes (K = 1..6
on one demonstration, one thread) with the W step compiled and in numpy.  Targets: < 10 ms per EM iteration,
< 10 us per update, on a 2-core machine.  Compilation is timed apart.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from etar import ETAR
from etar.synthetic import make_task, sample_demonstrations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3, help="timed fits per solver (best is reported)")
    parser.add_argument("--iterations", type=int, default=50)
    args = parser.parse_args()

    task = make_task(3, seed=0)
    data = sample_demonstrations(task, 6, 3000, seed=1)
    demos = [(s, f) for s, f, _ in data]
    t = time.perf_counter()
    ETAR(3, n_restarts=1).fit(demos[:1], max_iter=2)  # compile (or load the numba cache)
    compile_s = time.perf_counter() - t

    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print(f"data: 6 demonstrations x 3000 samples, n=3, m=3, K=3; {args.iterations} EM iterations")
    print(f"first call (compile or cache load): {compile_s:.2f} s")
    print(f"{'solver':<8} {'total s':>9} {'ms/iter':>9} {'objective':>14}  target ms/iter < 10")
    for solver in ("gd", "lbfgs"):
        best = None
        for _ in range(args.repeats):
            model = ETAR(3, n_restarts=1, solver=solver)
            t = time.perf_counter()
            model.fit(demos, max_iter=args.iterations, tol=0.0)
            total = time.perf_counter() - t
            assert model.fit_report_.n_iter == args.iterations
            best = total if best is None else min(best, total)
        print(f"{solver:<8} {best:>9.3f} {best / args.iterations * 1e3:>9.2f} {model.fit_report_.objective:>14.2f}")

    s, f = demos[0]
    filt = model.filter()
    filt.update(s[0], f[0])
    filt.update(s[1], f[1])
    rows = [(np.ascontiguousarray(s[t]), np.ascontiguousarray(f[t])) for t in range(len(s))]
    samples = []
    for _ in range(5):
        filt.reset()
        t = time.perf_counter()
        for st, fo in rows:
            filt.update(st, fo)
        samples.append((time.perf_counter() - t) / len(rows) * 1e6)
    print(f"online update: {min(samples):.2f} us per sample (best of 5 x {len(rows)}), target < 10 us")
    vote_fits(args.repeats)


def vote_fits(repeats: int) -> None:
    """What a run's phase-count vote fits: one demonstration of ~1100 samples, K = 1..6, four
    restarts and 200 iterations, on one thread (as in the learn stage's pool)."""
    import numba

    from etar import em

    task = make_task(3, seed=0)
    demo = [(s, f) for s, f, _ in sample_demonstrations(task, 1, 1100, seed=1)]
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        available = {kernel: em._compiled(kernel) for kernel in ("steps", "factors")}
        if not all(available.values()):
            print(f"the vote's fits: the compiled W step is not used here ({available}): nothing to compare")
            return
        print("the vote's fits (1 demonstration x 1100 samples, 4 restarts, 200 iterations, 1 thread), best of "
              f"{repeats}; numpy's W step (the reference the compiled one is checked against) beside it")
        for k in range(1, 7):
            times = {}
            for compiled in (True, False):
                em._CHECKED.update(steps=compiled, factors=compiled)
                best = float("inf")
                for _ in range(repeats):
                    t = time.perf_counter()
                    ETAR(k).fit(demo, max_iter=200, seed=0)
                    best = min(best, time.perf_counter() - t)
                times[compiled] = best
            print(f"  K={k}: {times[True] * 1e3:6.0f} ms compiled, {times[False] * 1e3:6.0f} ms numpy")
    finally:
        em._CHECKED.clear()
        numba.set_num_threads(before)


if __name__ == "__main__":
    main()
