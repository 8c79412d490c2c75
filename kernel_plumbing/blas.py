"""numpy's own BLAS and LAPACK, called from the per-cycle numba kernels.

numpy computes a cycle's small products (``J @ J.T``, ``J @ tau``, a 3x3 rotation times a
vector) and its solves through the OpenBLAS it bundles, whose kernels use fused
multiply-adds, their own summation order and a choice of kernel by CPU: a product
written out as a loop in numba gives other bits for 70-100 % of them
(``python bench/blas_bits.py``), so a compiled cycle that wrote them out would record
other numbers.  A kernel that calls the very functions numpy calls, in numpy's library,
with the arguments numpy passes, gets numpy's bits on any CPU (the library picks its
kernel for the CPU the same way for both callers).

The functions are reached by address: ``fn`` below is an int taken once from the loaded
library, and ``call_*`` are numba intrinsics that call a C function at such an address.
An address is an argument, not a constant compiled in, so the kernels stay in numba's
cache across processes.

``AVAILABLE`` says whether this numpy's library was found (the wheels' scipy-openblas,
64-bit integers) and, checked at import on random products of the cycle's shapes, gives
numpy's bits; where it is False (``WHY`` says why) the callers keep their numpy path,
which records the same numbers more slowly.

(numba's cache tracks only the file a kernel is defined in: after changing the
intrinsics here, clear etar/__pycache__/*.nb[ic] and robot_sim/__pycache__/*.nb[ic], as for kernel_plumbing.addresses.)
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from kernel_plumbing.addresses import JIT

ROW_MAJOR, NO_TRANS, TRANS, UPPER = 101, 111, 112, 121

_NATIVE = {types.int32: ir.IntType(32), types.int64: ir.IntType(64), types.float64: ir.DoubleType(),
           types.void: ir.VoidType()}


def foreign(ret, *argtypes):
    """A numba intrinsic ``call(address, *args)`` of a C function of these types (numba's
    int32, int64, float64; pointers as int64 addresses): BLAS's here, MuJoCo's in
    robot_sim.world.physics."""

    def codegen(context, builder, signature, llargs):
        fnty = ir.FunctionType(_NATIVE[ret], [_NATIVE[t] for t in argtypes])
        return builder.call(builder.inttoptr(llargs[0], fnty.as_pointer()), llargs[1:])

    names = ", ".join(f"a{i}" for i in range(len(argtypes)))
    scope = {"sig": ret(types.int64, *argtypes), "codegen": codegen}
    # an intrinsic's arity is its definition's: numba folds *args into one tuple argument
    exec(f"def call(typingctx, fn, {names}):\n    return sig, codegen\n", scope)  # noqa: S102
    return intrinsic(scope["call"])


_I32, _I64, _F64 = types.int32, types.int64, types.float64
# cblas_dgemv(order, trans, m, n, alpha, a, lda, x, incx, beta, y, incy)
call_gemv = foreign(types.void, _I32, _I32, _I64, _I64, _F64, _I64, _I64, _I64, _I64, _F64, _I64, _I64)
# cblas_dsyrk(order, uplo, trans, n, k, alpha, a, lda, beta, c, ldc)
call_syrk = foreign(types.void, _I32, _I32, _I32, _I64, _I64, _F64, _I64, _I64, _F64, _I64, _I64)
# dgesv_(&n, &nrhs, a, &lda, ipiv, b, &ldb, &info): every argument by address
call_gesv = foreign(types.void, _I64, _I64, _I64, _I64, _I64, _I64, _I64, _I64)
# cblas_ddot(n, x, incx, y, incy): numpy's ``a @ b`` of two vectors, and np.linalg.norm's sum of squares
call_dot = foreign(types.float64, _I64, _I64, _I64, _I64, _I64)
# cblas_dgemm(order, trans_a, trans_b, m, n, k, alpha, a, lda, b, ldb, beta, c, ldc): numpy's A @ B
call_gemm = foreign(types.void, _I32, _I32, _I32, _I64, _I64, _I64, _F64, _I64, _I64, _I64, _I64, _F64, _I64, _I64)
# dpotrf_(&uplo, &n, a, &lda, &info): numpy's cholesky, on a column-major copy
call_potrf = foreign(types.void, _I64, _I64, _I64, _I64, _I64)


@njit(**JIT)
def gemv(fn, a, x, y, trans):
    """``y = a @ x`` (``a.T @ x`` with ``trans``) for a C-contiguous float64 (m, n) ``a``, as
    numpy computes it: dgemv at ``fn`` (``GEMV``), row-major, unit strides."""
    m, n = a.shape
    call_gemv(fn, np.int32(ROW_MAJOR), np.int32(TRANS if trans else NO_TRANS), m, n, 1.0, a.ctypes.data, n,
              x.ctypes.data, 1, 0.0, y.ctypes.data, 1)


@intrinsic
def int64_at(typingctx, addr):
    """The int64 stored at the address ``addr`` (a LAPACK ``info``, in a kernel)."""
    if not isinstance(addr, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.load(builder.inttoptr(args[0], ir.IntType(64).as_pointer()))

    return types.int64(addr), codegen


@intrinsic
def int32_at(typingctx, addr):
    """The C int stored at the address ``addr`` (a field of a MuJoCo struct, in a kernel)."""
    if not isinstance(addr, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.load(builder.inttoptr(args[0], ir.IntType(32).as_pointer()))

    return types.int32(addr), codegen


def _library() -> tuple[ctypes.CDLL | None, str]:
    """numpy's BLAS library as loaded in this process, or None and why not."""
    blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
    if blas.get("name") != "scipy-openblas" or "USE64BITINT" not in blas.get("openblas configuration", ""):
        return None, f"numpy's BLAS is {blas.get('name')!r} ({blas.get('openblas configuration', '')}), not the wheels' scipy-openblas64"
    # the file numpy loaded: found in this process's map, so it is the one numpy calls
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError as e:  # not Linux
        return None, f"cannot see which libraries this process loaded ({e})"
    # numpy's own copy, beside its package (a scipy-openblas64 installed apart is another file)
    bundled = Path(np.__file__).resolve().parent.parent / "numpy.libs"
    for line in maps.splitlines():
        path = Path(line.split(maxsplit=5)[-1])
        if path.parent == bundled and "openblas64_" in path.name:
            try:
                return ctypes.CDLL(str(path)), ""
            except OSError as e:
                return None, f"numpy's OpenBLAS cannot be opened again ({e})"
    return None, f"numpy's scipy-openblas64 library is not mapped from {bundled} in this process"


def _address(lib: ctypes.CDLL, name: str) -> int:
    return ctypes.cast(getattr(lib, name), ctypes.c_void_p).value


_LIB, WHY = _library()
GEMV = SYRK = GESV = DOT = GEMM = 0
if _LIB is not None:
    try:
        GEMV, SYRK, GESV, DOT, GEMM = (_address(_LIB, n) for n in (
            "scipy_cblas_dgemv64_", "scipy_cblas_dsyrk64_", "scipy_dgesv_64_", "scipy_cblas_ddot64_",
            "scipy_cblas_dgemm64_"))
    except AttributeError as e:
        WHY = f"numpy's OpenBLAS lacks a function: {e}"
AVAILABLE = bool(GEMV and SYRK and GESV and DOT and GEMM)
# learning's Cholesky factors only (etar.softmax_regression): not needed by the cycle's kernels
POTRF = _address(_LIB, "scipy_dpotrf_64_") if AVAILABLE and hasattr(_LIB, "scipy_dpotrf_64_") else 0
