"""JSON text written by a numba kernel, byte for byte as ``orjson.dumps`` writes it.

Every message a run records is compact JSON from orjson (``services.runtime.messages``):
a kernel that writes a message's bytes straight from the arrays it computed must write
the same bytes, or the recordings would change.  Integers and literals are simple; a
float64 is orjson's shortest round-trip digits in its layout, which a kernel cannot
produce itself: ``JSON_DOUBLE`` is the address of a C++ function that does
(``kernel_plumbing/native/json_numbers.cpp``, C++17's ``std::to_chars``), called by
address as the kernels call BLAS and MuJoCo.  ``AVAILABLE`` is False where that
extension was not built (no C++ compiler at install; ``WHY`` says so): the callers then
write with orjson, the same bytes.

Checked against orjson itself: ``python bench/json_numbers.py`` (10^7 random bit
patterns and the layout's boundaries) and tests/kernel_plumbing/test_json_numbers.py.

(numba's cache tracks only the file a kernel is defined in: after changing these
helpers, clear the ``__pycache__/*.nb[ic]`` of the modules whose kernels use them.)
"""

from __future__ import annotations

import numpy as np
from numba import carray, njit, types
from numba.extending import intrinsic

from kernel_plumbing.addresses import JIT
from kernel_plumbing.blas import foreign

try:
    from kernel_plumbing._json_numbers import JSON_DOUBLE
    WHY = ""
except ImportError as exc:  # built without a C++ compiler
    JSON_DOUBLE, WHY = 0, f"kernel_plumbing._json_numbers is not built ({exc})"
AVAILABLE = bool(JSON_DOUBLE)

# the most bytes JSON_DOUBLE writes: '-', 17 digits, '.', 'e', '-', 3 exponent digits; or
# "-0.0000" and 17 digits
DOUBLE_BYTES = 32
# an int64 in decimal, '-' included
INT_BYTES = 20

# int (double x, char *out): x as orjson writes it, its length; -1 for NaN and infinity
_call_json_double = foreign(types.int32, types.float64, types.int64)


@intrinsic
def _uint8_pointer(typingctx, addr):
    if not isinstance(addr, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], context.get_value_type(signature.return_type))

    return types.CPointer(types.uint8)(addr), codegen


@njit(**JIT, inline="always")
def bytes_at(addr, n):
    """The ``n`` bytes at ``addr`` as a uint8 vector (a view, in a kernel)."""
    return carray(_uint8_pointer(addr), (n,))


def uint8_address(a: np.ndarray) -> int:
    """Where the bytes of ``a`` start, for ``bytes_at``."""
    if a.dtype != np.uint8 or not a.flags.c_contiguous:
        raise ValueError(f"need a contiguous uint8 array, got {a.dtype} with strides {a.strides}")
    return a.ctypes.data


def literal(text: str) -> np.ndarray:
    """``text`` as the uint8 array ``write_literal`` copies (UTF-8)."""
    return np.frombuffer(text.encode(), dtype=np.uint8).copy()


@njit(**JIT, inline="always")
def write_literal(out, pos, text):
    """``text`` (uint8) into ``out`` at ``pos``; the position after it."""
    n = len(text)
    out[pos:pos + n] = text
    return pos + n


@njit(**JIT)
def write_int(out, pos, value):
    """``value`` (int64) in decimal into ``out`` at ``pos``; the position after it."""
    if value == 0:
        out[pos] = 48
        return pos + 1
    if value < 0:
        out[pos] = 45
        pos += 1
    # the digits written from the last, then turned around in place; a negative value counts
    # down, so int64's minimum has no positive counterpart to overflow into
    start = pos
    v = value
    while v != 0:
        d = v % 10
        v = v // 10
        if d != 0 and value < 0:  # numba's % and // floor, as Python's do
            d = 10 - d
            v += 1
        out[pos] = 48 + d
        pos += 1
    i, j = start, pos - 1
    while i < j:
        out[i], out[j] = out[j], out[i]
        i += 1
        j -= 1
    return pos


@njit(**JIT, inline="always")
def write_bool(out, pos, value):
    if value:
        out[pos], out[pos + 1], out[pos + 2], out[pos + 3] = 116, 114, 117, 101  # true
        return pos + 4
    out[pos], out[pos + 1], out[pos + 2], out[pos + 3], out[pos + 4] = 102, 97, 108, 115, 101  # false
    return pos + 5


@njit(**JIT, inline="always")
def write_double(fn, out_at, pos, value):
    """``value`` as orjson writes it, at byte ``pos`` of the buffer at ``out_at``, through
    the C function at ``fn`` (``JSON_DOUBLE``); the position after it, or -1 when it is
    not finite (JSON cannot hold it: the caller's checked path names the field)."""
    n = _call_json_double(fn, value, out_at + pos)
    if n < 0:
        return -1
    return pos + n


@njit(**JIT)
def write_doubles(fn, out, out_at, pos, values):
    """``values`` (float64) as a JSON list, as orjson writes a list of floats; the position
    after it, or -1 when one of them is not finite."""
    out[pos] = 91  # [
    pos += 1
    for i in range(len(values)):
        if i:
            out[pos] = 44  # ,
            pos += 1
        pos = write_double(fn, out_at, pos, values[i])
        if pos < 0:
            return -1
    out[pos] = 93  # ]
    return pos + 1


@njit(**JIT)
def write_ints(out, pos, values):
    """``values`` (int64, or float64 whole numbers) as a JSON list; the position after it."""
    out[pos] = 91
    pos += 1
    for i in range(len(values)):
        if i:
            out[pos] = 44
            pos += 1
        pos = write_int(out, pos, np.int64(values[i]))
    out[pos] = 93
    return pos + 1
