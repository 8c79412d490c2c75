"""Encode / decode cost per message, for every message type.

    python bench/messages.py [--n 20000]

Prints microseconds per encode (dict -> JSON bytes) and per decode (bytes ->
checked dict) and the wire size, with realistic field values.  Each figure is
the best of ``--repeat`` rounds of ``--n`` calls (as timeit does): other jobs on
the machine only ever make a round slower.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from services.runtime.messages import MESSAGES


def sample(mtype):
    rng = np.random.default_rng(0)
    out = {}
    for f in mtype.fields:
        if f.optional:
            continue
        if "[" in f.type:
            n = f.length or 3
            out[f.name] = {"float": rng.normal(size=n).tolist(), "int": list(range(n)),
                           "str": ["plate_left"] * min(n, 1)}[f.base]
        else:
            out[f.name] = {"int": 123456789, "float": 0.123456789, "bool": True, "str": "reproduction",
                           "object": {"start": [0.6, -0.1, 0.4]}}[f.base]
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=20000)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    def best(fn, *a, **kw):
        times = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            for _ in range(args.n):
                fn(*a, **kw)
            times.append(time.perf_counter() - t)
        return min(times) / args.n * 1e6

    print(f"{'message':<18} {'bytes':>6} {'encode us':>10} {'decode us':>10}")
    for name, mtype in MESSAGES.items():
        values = sample(mtype)
        data = mtype.encode(**values)
        enc = best(mtype.encode, **values)
        dec = best(mtype.decode, data)
        print(f"{name:<18} {len(data):>6} {enc:>10.1f} {dec:>10.1f}")


if __name__ == "__main__":
    main()
