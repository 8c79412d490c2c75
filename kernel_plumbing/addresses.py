"""What the per-cycle numba kernels share: reaching preallocated buffers by address.

numba wraps every ndarray argument of a call in a freshly allocated MemInfo
(48 B through PyMem_RawMalloc, freed on return) and types each argument at the
call, so a per-cycle kernel called with arrays allocates however little it
computes, and costs microseconds before it starts.  Plain ints cost nothing to pass: the
per-cycle kernels (robot_sim.world.physics, robot_sim.krc.law, robot_sim.ati.sensor) take the
addresses of preallocated float64 buffers and view them with ``carray_at``/``farray_at``.
Whoever takes an address keeps the array alive and never resizes it.

And the per-cycle callers call a kernel's machine code through ``entry``, not through
numba's dispatcher, which types every argument again at every call: in a running cell
(the smoke scenario in one process, ``python bench/dispatch_cost.py``, 2026-12-03) the
cell's kernel calls cost 11.0 us a cycle through the dispatcher and 7.9 us as machine
code, the same code.

(numba's cache only tracks the file a kernel is defined in: after changing
these helpers, clear etar/__pycache__/*.nb[ic] and robot_sim/__pycache__/*.nb[ic]: the
kernels that use them live in both.)
"""

from __future__ import annotations

import numpy as np
from numba import carray, farray, njit, types
from numba.extending import intrinsic

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


def address(a: np.ndarray) -> int:
    """Where the float64 data of ``a`` starts, for ``carray_at``/``farray_at``."""
    if a.dtype != np.float64 or not (a.flags.c_contiguous or a.flags.f_contiguous):
        raise ValueError(f"need a contiguous float64 array, got {a.dtype} with strides {a.strides}")
    return a.ctypes.data


class HoldsAddresses:
    """A class whose objects keep the addresses of their own buffers for the kernels: a
    copy (copy, deepcopy, pickle) would keep the original's addresses, and its kernels
    would read and write the original's memory, or freed memory.  So it cannot be copied."""

    def __reduce_ex__(self, protocol):
        raise TypeError(f"{type(self).__name__} holds the addresses of its own buffers for its kernels and "
                        f"cannot be copied or pickled: make a new one")


def entry(kernel, signature: str):
    """``kernel``'s machine code for the argument types ``signature`` (numba's names:
    "int64, float64, boolean"), compiled now or loaded from numba's cache, to be called
    without the dispatcher.  It converts each argument to its declared type and checks
    nothing else: pass ints for addresses and int64, bools for booleans, floats for
    float64 (an array where an address belongs would be read as garbage)."""
    return kernel.compile(signature)


def addresses(n: int) -> str:
    """The signature of ``n`` int64 arguments (addresses and sizes), for ``entry``."""
    return ", ".join(["int64"] * n)


def _pointer_to(element):
    """A numba intrinsic that turns an integer address into a pointer to ``element``s."""

    def pointer(typingctx, addr):
        if not isinstance(addr, types.Integer):
            return None

        def codegen(context, builder, signature, args):
            return builder.inttoptr(args[0], context.get_value_type(signature.return_type))

        return types.CPointer(element)(addr), codegen

    return intrinsic(pointer)


_float64_pointer = _pointer_to(types.float64)
_int64_pointer = _pointer_to(types.int64)


@njit(**JIT, inline="always")
def int64_array_at(addr, n):
    """The int64 vector of ``n`` entries at ``addr`` (a view, in a kernel): a kernel's state
    between calls, or a table of addresses."""
    return carray(_int64_pointer(addr), (n,))


@njit(**JIT, inline="always")
def copy_at(src_at, dst_at, n):
    """Copy ``n`` float64 from the buffer at ``src_at`` to the one at ``dst_at`` (in a kernel)."""
    src, dst = carray(_float64_pointer(src_at), (n,)), carray(_float64_pointer(dst_at), (n,))
    for i in range(n):
        dst[i] = src[i]


def int64_address(a: np.ndarray) -> int:
    """Where the int64 data of ``a`` starts, for ``int64_array_at``."""
    if a.dtype != np.int64 or not a.flags.c_contiguous:
        raise ValueError(f"need a contiguous int64 array, got {a.dtype} with strides {a.strides}")
    return a.ctypes.data


@njit(**JIT, inline="always")
def carray_at(addr, shape):
    """The row-major float64 array of ``shape`` at ``addr`` (a view, in a kernel)."""
    return carray(_float64_pointer(addr), shape)


@njit(**JIT, inline="always")
def farray_at(addr, shape):
    """The column-major (Eigen's default) float64 array of ``shape`` at ``addr``."""
    return farray(_float64_pointer(addr), shape)
