"""numba's kernels compiled into its cache once, right after installing, two at a time.

    python -m services.run.kernel_cache      (make does it once, after installing)

A fresh checkout has no compiled kernel: the first process to call one compiles it
(about 40 s of CPU for a whole run: the cell's kernels at import, EM's on learning,
the estimator's and the commander's on reproducing) and writes numba's cache beside
its source, which every later process loads in well under a second.  Before, every
process of the first runs and tests compiled for itself at the same time: the two
test workers, the six services of a run over Zenoh.  Here two processes compile what
a run uses, one the learning, one the cell and the nodes, each by doing it: a small
run in one process with the smoke's model, and EM on synthetic demonstrations.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from etar.parsing import OneLineErrorParser


def _smoke_model() -> Path:
    """The smoke's model: the checkout's, or (an installed package, as in the image) the working folder's."""
    for base in (Path(__file__).resolve().parents[2], Path.cwd()):
        if (base / "scenarios" / "models" / "smoke.json").is_file():
            return base / "scenarios" / "models" / "smoke.json"
    raise SystemExit("kernel cache: no scenarios/models/smoke.json in the checkout or the working folder")


def _nodes(out: Path) -> None:
    """The cell, the sensor, the teacher, the estimator and the commander: a demonstration
    and a reproduction of the smoke's world in one process."""
    from services.run.options import RunOptions
    from services.run.runner import run
    from services.scenario import Scenario

    start = dict(start=[0.62, -0.06, 0.30], goal_x=0.57, max_seconds=1.0)
    scenario = Scenario.from_dict(dict(name="kernel_cache", world="valley", seed=0, model=str(_smoke_model()),
                                       stages=[{"demonstrate": dict(count=1, **start)},
                                               {"reproduce": dict(count=1, **start)}]))
    report = run(scenario, RunOptions(out=str(out), run_id="kernel-cache", transport="inproc", figures=False),
                 progress=lambda line: None)
    if report["error"]:
        raise SystemExit(f"kernel cache: the run that compiles the nodes' kernels failed: {report['error']}")


def _learning(out: Path) -> None:
    """EM's kernels: a fit to synthetic demonstrations, then the learned model's likelihood
    and posterior."""
    from etar.cli import main as etar

    if etar(["synth", "--out", str(out / "demos")]) != 0:
        raise SystemExit("kernel cache: etar synth failed")
    demos = sorted(str(p) for p in (out / "demos").glob("*.npz"))
    if etar(["learn", *demos, "--phases", "3", "--out", str(out / "model.json")]) != 0:
        raise SystemExit("kernel cache: etar learn failed")
    # scoring the models on the demonstrations (the learn stage's ETAR against STAR) and the
    # posterior phases: the forward pass and the smoother
    import numpy as np

    from etar.model import ETAR

    model = ETAR.load(str(out / "model.json"))
    with np.load(demos[0]) as demo:
        states, forces = demo["states"], demo["forces"]
    model.log_likelihood([(states, forces)])
    model.posterior(states, forces)


PARTS = {"nodes": _nodes, "learning": _learning}


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineErrorParser(prog="python -m services.run.kernel_cache", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    # one of the two processes the step starts (not for people)
    parser.add_argument("--part", choices=PARTS, help=argparse.SUPPRESS)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.part is not None:
        try:
            with tempfile.TemporaryDirectory(prefix="etar-kernel-cache-") as tmp:
                PARTS[args.part](Path(tmp))
        except KeyboardInterrupt:  # Ctrl-C reaches the whole group: the parent says it
            return 130
        return 0
    t0 = time.monotonic()
    parts = {}
    try:
        print("compiling numba's kernels into its cache (once after installing; a minute at most)", flush=True)
        for name in PARTS:
            parts[name] = subprocess.Popen([sys.executable, "-m", "services.run.kernel_cache", "--part", name],
                                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        said = {name: proc.communicate()[1] for name, proc in parts.items()}
    except KeyboardInterrupt:
        for proc in parts.values():
            proc.kill()
            proc.wait()
        print("kernel cache: interrupted; the kernels not compiled yet compile on first use", file=sys.stderr)
        return 130
    failed = [name for name, proc in parts.items() if proc.returncode != 0]
    for name in failed:
        print(said[name].strip()[-2000:], file=sys.stderr)
    if failed:
        print(f"kernel cache: compiling the {' and '.join(failed)} kernels failed", file=sys.stderr)
        return 1
    print(f"kernels compiled in {time.monotonic() - t0:.0f} s", flush=True)
    from robot_sim.arm.kinematics import PINOCCHIO_INPLACE_MISSING

    if PINOCCHIO_INPLACE_MISSING:  # the install goes on without the C++ part (setup.py): say so where it happened
        print(f"note: {PINOCCHIO_INPLACE_MISSING}; the cell runs on Pinocchio's bindings instead", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
