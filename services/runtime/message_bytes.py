"""A message's JSON bytes written by a kernel from arrays: the bytes ``MessageType.pack``
writes (orjson's), without the dict it builds.

A node that computes a message's numbers in arrays (a sensor's sample) puts them in a
``MessageBytes``' two value arrays, ``ints`` and ``floats``, at the places its
``slots`` say, and ``write`` turns them into the message's bytes in one compiled call
(``kernel_plumbing.json_text``: the numbers as orjson writes them).  The keys, their
order and each field's kind come from the message's definition, the one home of a
message's layout.  The dict ``pack`` also returns is made only for a subscriber in the
same process (``message``).

What it cannot write it does not: a value JSON cannot hold (NaN, infinity) makes
``write`` return None, and the caller goes the checked way (``pack``), which names the
field.  Where the JSON writer is not built (``kernel_plumbing.json_text.AVAILABLE``),
``MessageBytes.available`` is False and the callers pack as before.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from kernel_plumbing.addresses import JIT, address, addresses, carray_at, entry, int64_address, int64_array_at
from kernel_plumbing.json_text import (AVAILABLE, DOUBLE_BYTES, INT_BYTES, JSON_DOUBLE, bytes_at, uint8_address,
                                       write_bool, write_double, write_doubles, write_int, write_ints)
from services.runtime.messages import MessageType

# a field's kind: how its values are written, from which array
INT, FLOAT, BOOL, INTS, FLOATS, WHOLE_FLOATS = range(6)
# the layout's columns, a row a field: kind, where its key starts in ``keys``, the key's
# length, where its values start in ``ints`` or ``floats``, how many (scalars: 1)
_KIND, _KEY_AT, _KEY_LEN, _VALUE_AT, _COUNT = range(5)


@njit(**JIT)
def _write_at(fn, layout_at, n_fields, keys_at, n_keys, ints_at, n_ints, floats_at, n_floats, out_at, n_out):
    """The message into the buffer at ``out_at``: its length, or -1 for a non-finite float."""
    layout = int64_array_at(layout_at, n_fields * 5).reshape((n_fields, 5))
    keys, out = bytes_at(keys_at, n_keys), bytes_at(out_at, n_out)
    ints = int64_array_at(ints_at, max(n_ints, 1))
    floats = carray_at(floats_at, (max(n_floats, 1),))
    pos = 0
    for f in range(n_fields):
        kind, at, count = layout[f, _KIND], layout[f, _VALUE_AT], layout[f, _COUNT]
        k0 = layout[f, _KEY_AT]
        k1 = k0 + layout[f, _KEY_LEN]
        out[pos:pos + k1 - k0] = keys[k0:k1]
        pos += k1 - k0
        if kind == INT:
            pos = write_int(out, pos, ints[at])
        elif kind == BOOL:
            pos = write_bool(out, pos, ints[at] != 0)
        elif kind == FLOAT:
            pos = write_double(fn, out_at, pos, floats[at])
        elif kind == INTS:
            pos = write_ints(out, pos, ints[at:at + count])
        elif kind == WHOLE_FLOATS:
            pos = write_ints(out, pos, floats[at:at + count])
        else:
            pos = write_doubles(fn, out, out_at, pos, floats[at:at + count])
        if pos < 0:
            return -1
    out[pos] = 125  # }
    return pos + 1


_WRITE = entry(_write_at, addresses(11))
# for a kernel that computes a message's numbers and writes it in the same call: it takes
# ``MessageBytes.kernel_args`` and returns what ``_write_at`` does
WRITE_AT = _write_at


class MessageBytes:
    """The bytes of one message type from two value arrays.  ``slots[name]`` is the field's
    (array, start, count): its values go to ``ints`` or ``floats`` there.  ``whole`` names
    int fields whose values are kept as float64 whole numbers (a sensor's counts, as its
    kernel computes them): they are written as integers."""

    available = AVAILABLE

    def __init__(self, mtype: MessageType, whole: tuple = ()):
        self.mtype = mtype
        layout, keys, slots = [], bytearray(), {}
        n_int = n_float = 0
        bound = 1
        for i, f in enumerate(mtype.fields):
            if f.optional:
                raise ValueError(f"{mtype.name}: field {f.name!r} is optional; MessageBytes writes every field")
            n = f.length if "[" in f.type else 1
            if n is None:
                raise ValueError(f"{mtype.name}: field {f.name!r} ({f.type}) has no fixed length")
            if f.base == "int" and f.name not in whole:
                kind, at = (INTS if "[" in f.type else INT), n_int
                n_int += n
            elif f.base == "bool":
                kind, at = BOOL, n_int
                n_int += 1
            elif f.base in ("float", "int"):
                kind = WHOLE_FLOATS if f.name in whole else FLOATS if "[" in f.type else FLOAT
                if f.name in whole and "[" not in f.type:
                    raise ValueError(f"{mtype.name}: whole numbers are for int arrays, not {f.name!r}")
                at = n_float
                n_float += n
            else:
                raise ValueError(f"{mtype.name}: field {f.name!r} ({f.type}) is not a number")
            key = ("{" if i == 0 else ",") + f'"{f.name}":'
            layout.append((kind, len(keys), len(key.encode()), at, n))
            keys += key.encode()
            slots[f.name] = ("ints" if kind in (INT, INTS, BOOL) else "floats", at, n)
            bound += len(key.encode()) + n * (DOUBLE_BYTES + 1) + 2
        self.slots = slots
        self.ints = np.zeros(max(n_int, 1), dtype=np.int64)
        self.floats = np.zeros(max(n_float, 1), dtype=np.float64)
        self._layout = np.array(layout, dtype=np.int64)
        self._keys = np.frombuffer(bytes(keys), dtype=np.uint8).copy()
        self._out = np.zeros(max(bound, INT_BYTES), dtype=np.uint8)
        self._args = (JSON_DOUBLE, int64_address(self._layout), len(layout), uint8_address(self._keys),
                      len(self._keys), int64_address(self.ints), n_int, address(self.floats), n_float,
                      uint8_address(self._out), len(self._out))

    def write(self) -> bytes | None:
        """The message's bytes from the value arrays; None when a float is not finite."""
        n = _WRITE(*self._args)
        return None if n < 0 else self.written(n)

    @property
    def kernel_args(self) -> tuple:
        """``WRITE_AT``'s arguments for these arrays; after it, ``written(n)`` is the message."""
        return self._args

    def written(self, n: int) -> bytes:
        """The first ``n`` bytes ``WRITE_AT`` wrote."""
        return self._out[:n].tobytes()

    def message(self) -> dict:
        """The dict ``pack`` returns with these bytes (what they decode to)."""
        out = {}
        for f in self.mtype.fields:
            array, at, n = self.slots[f.name]
            values = (self.ints if array == "ints" else self.floats)[at:at + n]
            if f.base == "int":
                values = values.astype(np.int64) if array == "floats" else values
            v = values.tolist()
            out[f.name] = v if "[" in f.type else (bool(v[0]) if f.base == "bool" else v[0])
        return out
