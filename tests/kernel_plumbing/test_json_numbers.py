"""The kernels' JSON writer (kernel_plumbing.json_text) against orjson, the writer of every
recorded message: the same bytes for any finite float64 and any int64."""

import numpy as np
import orjson
import pytest

from kernel_plumbing import json_text
from kernel_plumbing.json_text import (AVAILABLE, JSON_DOUBLE, WHY, uint8_address, write_doubles, write_int,
                                       write_ints)

pytestmark = pytest.mark.skipif(not AVAILABLE, reason=WHY or "the JSON number writer is not built")

# where orjson's layout changes (fixed below 1e16 and from 1e-5 on), the ends of float64
# and the values a cycle's messages carry
EDGES = [0.0, -0.0, 1e-5, -1e-5, np.nextafter(1e-5, 0), np.nextafter(1e-5, 1), 1e16, np.nextafter(1e16, 0),
         9999999999999998.0, 1e15, 123.0, 0.1, 0.2, 0.3, 1 / 3, 2 / 3, 5e-324, -5e-324, 2.2250738585072014e-308,
         2.225073858507201e-308, 1.7976931348623157e308, -1.7976931348623157e308, 1e22, 1e23, 1e-7, 9.5e-6,
         0.5, 1.0, -1.0, 2.0**53, 2.0**53 + 2, 2.0**63, 1e-300, 4.35, 0.001, 1234.5678, 0.000123]


def written(values: np.ndarray) -> bytes:
    out = np.zeros(len(values) * json_text.DOUBLE_BYTES + 2, np.uint8)
    end = write_doubles(JSON_DOUBLE, out, uint8_address(out), 0, np.ascontiguousarray(values, dtype=np.float64))
    assert end >= 0
    return out[:end].tobytes()


def test_the_boundaries_and_the_ends_of_float64_are_written_as_orjson_writes_them():
    values = np.array(EDGES, dtype=np.float64)
    assert written(values) == orjson.dumps(values.tolist())
    for x in EDGES:  # one at a time too: a mismatch names its value
        assert written(np.array([x])) == orjson.dumps([float(x)]), repr(x)


def test_random_bit_patterns_are_written_as_orjson_writes_them():
    """Every exponent and mantissa alike (random bits, not random values), subnormals included."""
    bits = np.random.default_rng(20261206).integers(0, 2**64, size=1_000_000, dtype=np.uint64)
    values = bits.view(np.float64)
    values = values[np.isfinite(values)]
    assert written(values) == orjson.dumps(values.tolist())


def test_random_values_of_a_cycles_magnitudes_are_written_as_orjson_writes_them():
    rng = np.random.default_rng(7)
    values = rng.normal(size=200_000) * 10.0 ** rng.integers(-8, 18, size=200_000)
    assert written(values) == orjson.dumps(values.tolist())


def test_a_value_json_cannot_hold_is_refused_not_written():
    out = np.zeros(256, np.uint8)
    for bad in (np.nan, np.inf, -np.inf):
        assert write_doubles(JSON_DOUBLE, out, uint8_address(out), 0, np.array([1.0, bad])) == -1


def test_integers_are_written_as_orjson_writes_them():
    rng = np.random.default_rng(3)
    values = np.concatenate([rng.integers(-2**63, 2**63 - 1, size=100_000, dtype=np.int64, endpoint=True),
                             np.array([0, 1, -1, 9, 10, -10, 2**63 - 1, -2**63], dtype=np.int64)])
    out = np.zeros(len(values) * 21 + 2, np.uint8)
    end = write_ints(out, 0, values)
    assert out[:end].tobytes() == orjson.dumps(values.tolist())
    single = np.zeros(32, np.uint8)
    assert single[:write_int(single, 0, -2**63)].tobytes() == b"-9223372036854775808"
