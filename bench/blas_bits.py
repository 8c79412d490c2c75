"""How often a compiled product gives other bits than numpy's small products, which go
through OpenBLAS (fused multiply-adds, its own summation order, kernels chosen by CPU):
written out as a loop (numba, no fastmath), and called from numba in numpy's own library
(kernel_plumbing.blas, what the cell's kernels do).

    python bench/blas_bits.py [--trials 20000] [--seed 1]

Exit code 0: every product called from numba in numpy's library had numpy's bits; 1: one
did not; 2: numpy's library cannot be reached here (the loop column alone is printed).

The cell's recorded values pass through such products (the external-wrench estimate's
J J^T and J tau, the commander's matvecs, the teacher's rotations), so compiling them
changes recordings unless the counts are zero.  The measurements (2026-12-03,
this VM, OpenBLAS 0.3.31 DYNAMIC_ARCH): docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from kernel_plumbing import blas  # noqa: E402


@njit(cache=False)
def _matvec(A, b, out):
    n, m = A.shape
    for i in range(n):
        s = 0.0
        for j in range(m):
            s += A[i, j] * b[j]
        out[i] = s


@njit(cache=False)
def _matmul(A, B, out):
    n, k = A.shape
    for i in range(n):
        for j in range(B.shape[1]):
            s = 0.0
            for m in range(k):
                s += A[i, m] * B[m, j]
            out[i, j] = s


@njit(cache=False)
def _syrk(a, c):
    n, k = a.shape
    blas.call_syrk(blas.SYRK, np.int32(blas.ROW_MAJOR), np.int32(blas.UPPER), np.int32(blas.NO_TRANS),
                   n, k, 1.0, a.ctypes.data, k, 0.0, c.ctypes.data, n)
    for i in range(n):
        for j in range(i):
            c[i, j] = c[j, i]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--trials", type=int, default=20000, help="random products of each kind (default 20000)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    if args.trials < 1:
        ap.error("--trials must be >= 1")
    rng = np.random.default_rng(args.seed)
    kinds = ("3x3 @ 3", "3x3^T @ 3", "3x3 @ 3x3", "6x7 @ 7", "6x7 @ 6x7^T", "v . v (3)")
    differ = dict.fromkeys(kinds, 0)
    called = dict.fromkeys(("3x3 @ 3", "3x3^T @ 3", "6x7 @ 7", "6x7 @ 6x7^T"), 0)
    o3, o6, o33, o66 = np.empty(3), np.empty(6), np.empty((3, 3)), np.empty((6, 6))
    for _ in range(args.trials):
        A, B, b = rng.standard_normal((3, 3)), rng.standard_normal((3, 3)), rng.standard_normal(3)
        J, t = rng.standard_normal((6, 7)), rng.standard_normal(7)
        _matvec(A, b, o3)
        differ["3x3 @ 3"] += not np.array_equal(o3, A @ b)
        _matvec(np.ascontiguousarray(A.T), b, o3)
        differ["3x3^T @ 3"] += not np.array_equal(o3, A.T @ b)
        _matmul(A, B, o33)
        differ["3x3 @ 3x3"] += not np.array_equal(o33, A @ B)
        _matvec(J, t, o6)
        differ["6x7 @ 7"] += not np.array_equal(o6, J @ t)
        _matmul(J, np.ascontiguousarray(J.T), o66)
        differ["6x7 @ 6x7^T"] += not np.array_equal(o66, J @ J.T)
        differ["v . v (3)"] += not (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]) == b @ b
        if blas.AVAILABLE:
            blas.gemv(blas.GEMV, A, b, o3, False)
            called["3x3 @ 3"] += not np.array_equal(o3, A @ b)
            blas.gemv(blas.GEMV, A, b, o3, True)
            called["3x3^T @ 3"] += not np.array_equal(o3, A.T @ b)
            blas.gemv(blas.GEMV, J, t, o6, False)
            called["6x7 @ 7"] += not np.array_equal(o6, J @ t)
            _syrk(J, o66)
            called["6x7 @ 6x7^T"] += not np.array_equal(o66, J @ J.T)
    print(f"numpy {np.__version__}; products whose bits differ from numpy's, of {args.trials} each:")
    print(f"  {'':12s} {'loop':>16s}   {'numpy BLAS from numba':>22s}")
    for what in kinds:
        n = differ[what]
        via = (f"{called[what]:6d}  ({100 * called[what] / args.trials:.1f} %)" if blas.AVAILABLE and what in called
               else "-" if blas.AVAILABLE else "n/a")
        print(f"  {what:12s} {n:6d}  ({100 * n / args.trials:5.1f} %)   {via:>22s}")
    if not blas.AVAILABLE:
        print(f"numpy's library from numba: not available here ({blas.WHY})")
    if not blas.AVAILABLE:
        return 2
    return 1 if any(called.values()) else 0


if __name__ == "__main__":
    raise SystemExit(main())
