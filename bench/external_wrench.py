"""The KRC's external-wrench estimate per call: the compiled kernel (kernel_plumbing.blas,
numpy's own BLAS and LAPACK) against the numpy path it replaced, on a running valley cell,
alternately.

    python bench/external_wrench.py [--calls 20000] [--rounds 4]

Both include taking the tcp Jacobian from Pinocchio; both give the same bits
(tests/robot_sim/test_blas.py).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pinocchio as pin  # noqa: E402

from robot_sim import cell as cell_module  # noqa: E402
from robot_sim.world.tasks import valley


def per_call_ns(f, calls: int) -> float:
    t = time.perf_counter_ns()
    for _ in range(calls):
        f()
    return (time.perf_counter_ns() - t) / calls


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--calls", type=int, default=20000, help="calls per timing (default 20000)")
    ap.add_argument("--rounds", type=int, default=4, help="alternations (default 4)")
    args = ap.parse_args(argv)
    if args.calls < 1 or args.rounds < 1:
        ap.error("--calls and --rounds must be >= 1")
    if cell_module._EXTERNAL_WRENCH is None:
        print(f"the compiled estimate is not in use here: {cell_module.EXTERNAL_WRENCH_WHY}")
        return 1
    cell = cell_module.RobotCell(valley(), seed=0)
    cell.start()
    for _ in range(50):
        cell.begin_cycle()
        cell.end_cycle()
    kin = cell.kin

    def numpy_path():
        return cell_module._external_wrench_numpy(kin.jacobian("tcp", pin.ReferenceFrame.LOCAL), cell._tau_ext,
                                                  cell._JJt, cell._Jtau)

    print(f"external-wrench estimate, ns per call ({args.calls} calls a timing):")
    for _ in range(args.rounds):
        compiled, numpy = per_call_ns(cell._external_wrench_tcp, args.calls), per_call_ns(numpy_path, args.calls)
        print(f"  compiled {compiled:7.0f}   numpy {numpy:7.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
