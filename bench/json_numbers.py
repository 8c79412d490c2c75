"""The kernels' JSON number writer (kernel_plumbing.json_text) against orjson, the writer of
every recorded message: bytes compared on random float64 bit patterns (every exponent and
mantissa alike, subnormals included), on random values of a cycle's magnitudes, and on
random int64; the time a number takes each way.

    python bench/json_numbers.py [--count 10000000] [--seed 1]

Exit code 0: every number written as orjson writes it; 1: one was not (its value is
printed); 2: the writer is not built here.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import orjson

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from etar.parsing import OneLineErrorParser  # noqa: E402
from kernel_plumbing import json_text  # noqa: E402


def ours(values: np.ndarray) -> tuple[bytes, float]:
    out = np.ones(len(values) * json_text.DOUBLE_BYTES + 2, np.uint8)  # its pages touched before the clock
    at = json_text.uint8_address(out)
    json_text.write_doubles(json_text.JSON_DOUBLE, out, at, 0, values[:2])  # compiled before it is timed
    t = time.perf_counter()
    end = json_text.write_doubles(json_text.JSON_DOUBLE, out, at, 0, values)
    return out[:end].tobytes(), time.perf_counter() - t


def orjsons(values: np.ndarray) -> tuple[bytes, float]:
    listed = values.tolist()
    t = time.perf_counter()
    data = orjson.dumps(listed)
    return data, time.perf_counter() - t


def first_difference(values: np.ndarray) -> str:
    for x in values.tolist():
        a, _ = ours(np.array([x]))
        if a != orjson.dumps([x]):
            return f"{x!r}: orjson {orjson.dumps(x)!r}, ours {a[1:-1]!r}"
    return "none found one at a time"


def main(argv=None) -> int:
    parser = OneLineErrorParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=10_000_000, help="numbers of each kind (default 10^7)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    if args.count < 1:
        parser.error(f"--count: {args.count} is not a positive number")
    if not json_text.AVAILABLE:
        print(f"bench/json_numbers.py: {json_text.WHY}", file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    bits = rng.integers(0, 2**64, size=args.count, dtype=np.uint64).view(np.float64)
    cases = {
        "random bit patterns": bits[np.isfinite(bits)],
        "a cycle's magnitudes (normal x 10^-8..10^17)": rng.normal(size=args.count) * 10.0 ** rng.integers(-8, 18, size=args.count),
    }
    failed = False
    print(f"{'float64':<46} {'numbers':>10} {'same':>5} {'ours ns':>8} {'orjson ns':>10}")
    for name, values in cases.items():
        (a, t_ours), (b, t_orjson) = ours(values), orjsons(values)
        same = a == b
        failed |= not same
        print(f"{name:<46} {len(values):>10} {'yes' if same else 'NO':>5} {t_ours / len(values) * 1e9:>8.1f} "
              f"{t_orjson / len(values) * 1e9:>10.1f}")
        if not same:
            print(f"  first difference: {first_difference(values)}")
    ints = rng.integers(-2**63, 2**63 - 1, size=args.count, dtype=np.int64, endpoint=True)
    out = np.ones(len(ints) * 21 + 2, np.uint8)
    json_text.write_ints(out, 0, ints[:2])
    t = time.perf_counter()
    end = json_text.write_ints(out, 0, ints)
    t_ours = time.perf_counter() - t
    b, t_orjson = orjsons(ints)
    same = out[:end].tobytes() == b
    failed |= not same
    print(f"{'int64, random':<46} {len(ints):>10} {'yes' if same else 'NO':>5} {t_ours / len(ints) * 1e9:>8.1f} "
          f"{t_orjson / len(ints) * 1e9:>10.1f}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
