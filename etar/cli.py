"""``etar``: learn ETAR models from demonstrations and inspect them.

    etar learn DEMOS... --phases auto|N --out MODEL
    etar inspect MODEL [--demos DEMOS...]
    etar synth --out DIR          (synthetic demonstrations for trying it out)

Demonstrations are ``.npz`` files with arrays ``states`` (T, n) and
``forces`` (T, m), optionally ``phases`` (T-1,) ground truth and ``dt`` (s).
A command writing one file takes ``--out FILE``, one writing several ``--out DIR``.

Every flag and file is checked before any work starts: a mistake is one line,
``etar <command>: error: <flag or file>: <problem>, got <value>``, exit code 2;
a run that fails after it started is one line too, exit code 1.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import textwrap
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from etar.demonstrations import DemonstrationError, check_demonstration, check_true_labels
from etar.interrupts import interrupt_behind
from etar.parsing import CommandParser, cannot_write_in, one_line, reader_gone
from etar.vocabulary import CRITERIA, FEATURES, MAX_PHASES, STATES, TRANSITIONS

USAGE_ERROR = 2  # a flag or a file the command cannot use: nothing was done
RUN_FAILED = 1  # the work started and failed

_NO_VALUE = object()


class UsageError(ValueError):
    """A flag or a file the command cannot use: ``name: problem, got value``."""

    def __init__(self, name: str, problem: str, value=_NO_VALUE):
        text = f"{name}: {problem}"
        if value is not _NO_VALUE:
            value = value.tolist() if hasattr(value, "tolist") else value
            text += f", got {value!r}"
        super().__init__(text)


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("etar-testbench")
    except PackageNotFoundError:
        return "unknown"


# --------------------------------------------------------------------------
# demonstration files
# --------------------------------------------------------------------------


def load_npz_demonstration(path) -> dict:
    """{'states', 'forces', optional 'phases', 'dt'} from one .npz file, or a
    ``DemonstrationError`` naming the file and the field at fault."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            out = {k: data[k] for k in data.files}
    except FileNotFoundError:
        raise DemonstrationError(f"{path}: no such file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise DemonstrationError(f"{path}: not a readable .npz file ({exc})") from None
    except (AttributeError, TypeError):  # np.load of a plain .npy gives an array: no .files, no `with`
        raise DemonstrationError(f"{path}: not a .npz archive (a single array?)") from None
    for key in ("states", "forces"):
        if key not in out:
            raise DemonstrationError(f"{path}: field '{key}' is missing (found: {sorted(out)})")
    if "phases" in out:
        check_true_labels(out["phases"], np.shape(out["states"])[0] if np.ndim(out["states"]) else 0, str(path))
    return out


# suffix -> function(path) -> list of demonstration dicts; other layers register
# their formats here (services adds .mcap recordings) so etar stays format-agnostic.
# A dict may carry 'warning' (printed once every file is accepted).
LOADERS = {".npz": lambda p: [load_npz_demonstration(p)]}

# suffix -> function(path) -> what episode the file holds ('demonstration', 'reproduction',
# ...) or None if it does not say; read cheaply, before any file is loaded: `etar learn`
# takes demonstrations only.  A suffix without an entry holds demonstrations.
EPISODE_KINDS: dict[str, Callable] = {}


def _check_files(paths, flag: str) -> list[Path]:
    """Every file exists and has a format we read: refused before any is loaded."""
    if not paths:
        raise UsageError(flag, "no demonstration files given")
    out = []
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise UsageError(str(p), "no such file")
        if p.is_dir():
            raise UsageError(str(p), "is a folder, not a demonstration file (give its files: "
                                     f"{p}/*{next(iter(LOADERS))})")
        if p.suffix not in LOADERS:
            raise UsageError(str(p), f"unsupported demonstration file type (expected {' or '.join(sorted(LOADERS))}), "
                                     f"got suffix {p.suffix!r}")
        out.append(p)
    return out


def _load(paths) -> list[tuple[Path, dict]]:
    """(file, demonstration) pairs; a file may hold several demonstrations."""
    return [(Path(p), d) for p in paths for d in LOADERS[Path(p).suffix](Path(p))]


def _checked_arrays(loaded, n: int | None = None, m: int | None = None, like: str = "") -> list[tuple]:
    """The (states, forces) of every loaded demonstration, all of the same widths, or a
    ``UsageError`` naming the file (``n``, ``m``: the widths they must have, ``like``: whose)."""
    pairs = []
    for path, d in loaded:
        try:
            s, f = check_demonstration(d["states"], d["forces"], n=n, m=m)
        except DemonstrationError as exc:
            problem = str(exc).removeprefix("demonstration 0: ")
            raise UsageError(str(path), problem + (f" (as {like})" if like and "columns" in problem else "")) \
                from None
        if n is None:
            n, m, like = s.shape[1], f.shape[1], f"in {path}"
        pairs.append((s, f))
    return pairs


def _warn(command: str, loaded) -> None:
    for _, d in loaded:
        if d.get("warning"):
            _say(f"etar {command}: warning: {d['warning']}")


# --------------------------------------------------------------------------
# flag checks (each raises UsageError naming the flag and the value)
# --------------------------------------------------------------------------


def _at_least(flag: str, value, low: int, why: str = "", high: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise UsageError(flag, f"must be an integer >= {low}{why}", value)
    if high is not None and value > high:
        raise UsageError(flag, f"must be an integer <= {high}", value)
    return value


def _positive(flag: str, value, unit: str = "") -> float:
    if not (math.isfinite(value) and value > 0):
        raise UsageError(flag, f"must be a finite number > 0{unit}", value)
    return float(value)


def _writable_folder(flag: str, value, folder: Path) -> None:
    """``folder`` exists as a folder this process may write in, or can be created."""
    p = folder
    while not p.exists() and p != p.parent:
        if p.is_symlink():
            raise UsageError(flag, f"{p} is a broken symbolic link", value)
        p = p.parent
    if not p.is_dir():
        raise UsageError(flag, f"{p} is a file, not a folder", value)
    why = cannot_write_in(p)
    if why:
        raise UsageError(flag, f"cannot write in {p} ({why[0].lower() + why[1:]})", value)


def _path(flag: str, value: str) -> Path:
    """A path flag's value; an empty one is refused, as Path('') would be the current folder."""
    if not str(value).strip():
        raise UsageError(flag, "an empty path names no file or folder", value)
    return Path(value).expanduser()


def _out_file(flag: str, value: str, what: str) -> Path:
    """``--out FILE``: a file that can be written (its folder is created)."""
    path = _path(flag, value)
    if path.is_dir():
        raise UsageError(flag, f"is a folder; give the {what} file to write", value)
    if path.exists() and not os.access(path, os.W_OK):
        raise UsageError(flag, "exists and cannot be overwritten (permission denied)", value)
    _writable_folder(flag, value, path.parent)
    return path.resolve()


def _out_folder(flag: str, value: str) -> Path:
    """``--out DIR``: a folder that exists or can be created, and can be written in."""
    path = _path(flag, value)
    if path.exists() and not path.is_dir():
        raise UsageError(flag, "is a file, not a folder", value)
    _writable_folder(flag, value, path)
    return path


# --------------------------------------------------------------------------
# learn
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class LearnJob:
    """What ``etar learn`` does, every value checked."""

    files: list  # the demonstration files, as given
    loaded: list  # (file, demonstration dict) pairs
    pairs: list  # (states (T, n), forces (T, m)) of each, checked
    out: Path
    phases: int | None  # None: choose among ``candidates`` by ``criterion``
    candidates: tuple
    criterion: str
    selection: str
    transitions: str
    seed: int
    restarts: int
    max_iter: int
    tol: float
    solver: str
    dt: float


def check_learn(args) -> LearnJob:
    if args.phases == "auto":
        phases = None
    else:
        try:
            phases = int(args.phases)
        except ValueError:
            phases = 0
        if not 1 <= phases <= MAX_PHASES:
            raise UsageError("--phases", f"must be 'auto' or an integer in 1..{MAX_PHASES}", args.phases)
    if phases is None:
        _at_least("--max-phases", args.max_phases, 1, high=MAX_PHASES)
    seed = _at_least("--seed", args.seed, 0)
    restarts = _at_least("--restarts", args.restarts, 1)
    max_iter = _at_least("--max-iter", args.max_iter, 1)
    tol = _positive("--tol", args.tol, " (nats per sample per iteration)")
    dt = None if args.dt is None else _positive("--dt", args.dt, " s")
    files = _check_files(args.demos, "DEMOS")
    out = _out_file("--out", args.out, "model")
    if out in {p.resolve() for p in files}:
        raise UsageError("--out", "is one of the demonstration files; it would be overwritten", args.out)
    for p in files:
        kind = EPISODE_KINDS[p.suffix](p) if p.suffix in EPISODE_KINDS else None
        if kind is not None and kind != "demonstration":
            raise UsageError(str(p), f"is a {kind} recording, not a demonstration (its metadata's episode_kind)",
                             kind)

    loaded = _load(files)
    pairs = _checked_arrays(loaded)
    if dt is None:
        for i, (path, d) in enumerate(loaded):  # one model, one sample period: the files' must agree
            try:
                period = float(d.get("dt", 0.01))
            except (TypeError, ValueError):
                period = math.nan
            if not (math.isfinite(period) and period > 0):
                raise UsageError(str(path), "field 'dt' must be a sample period > 0 s (or pass --dt)", d["dt"])
            if i == 0:
                first, dt = path, period
            elif "dt" in d and not math.isclose(period, dt, rel_tol=1e-9):
                raise UsageError(str(path), f"field 'dt' differs from {first}'s {dt:g} s: demonstrations learned "
                                            "together must share their sample period (or pass --dt)", d["dt"])
    candidates = tuple(range(1, args.max_phases + 1)) if phases is None else ()
    _check_data_size(loaded, pairs, phases, args.transitions, args.selection)
    return LearnJob(files=files, loaded=loaded, pairs=pairs, out=out, phases=phases, candidates=candidates,
                    criterion=args.criterion, selection=args.selection if len(pairs) > 1 else "pooled",
                    transitions=args.transitions, seed=seed, restarts=restarts, max_iter=max_iter, tol=tol,
                    solver=args.solver, dt=dt)


def _check_data_size(loaded, pairs, phases: int | None, transitions: str, selection: str) -> None:
    """More steps than free parameters, as the fits need (``ETAR.fit``, ``etar.selection``)."""
    from etar.model import ETAR

    n, m = pairs[0][0].shape[1], pairs[0][1].shape[1]
    d = n if transitions == "state" else m
    steps = sum(s.shape[0] - 1 for s, _ in pairs)
    if phases is not None:
        p = ETAR.count_free_parameters(phases, n, m, d)
        if p > steps:
            raise UsageError("--phases", f"a {phases}-phase model has {p} free parameters, more than the {steps} "
                                         "steps of the demonstrations (record more or use fewer phases)", phases)
        return
    p = ETAR.count_free_parameters(1, n, m, d)
    if selection == "per_demonstration" and len(pairs) > 1:
        for (path, _), (s, _) in zip(loaded, pairs):
            if p > s.shape[0] - 1:
                raise UsageError(str(path), f"has {s.shape[0]} samples: its {s.shape[0] - 1} steps are fewer than "
                                            f"the {p} free parameters of even a 1-phase model, and each demonstration "
                                            "chooses its number of phases alone (--selection pooled scores them "
                                            "together)")
    elif p > steps:
        if len(loaded) == 1:
            raise UsageError(str(loaded[0][0]), f"its {steps} steps are fewer than the {p} free parameters of even a "
                                                "1-phase model", f"{steps + 1} samples")
        raise UsageError("DEMOS", f"their {steps} steps are fewer than the {p} free parameters of even a 1-phase "
                                  "model", [str(path) for path, _ in loaded])


def learn(job: LearnJob) -> int:
    from etar.model import ETAR
    from etar.selection import fit_order
    from etar.task import TaskError, learn_task

    demos = [d for _, d in job.loaded]
    pairs = job.pairs
    options = dict(n_restarts=job.restarts, solver=job.solver)
    if job.phases is None:
        _say(f"selecting the number of phases by {job.criterion.upper()} over {list(job.candidates)} "
             f"from {len(pairs)} demonstration(s)")
        # with one demonstration, voting is the pooled choice and one more fit
        model, selection = fit_order(pairs, job.candidates, job.criterion, job.selection,
                                     transitions=job.transitions, seed=job.seed, max_iter=job.max_iter,
                                     tol=job.tol, progress=_say, **options)
        model.metadata["selection"] = selection
    else:
        model = ETAR(job.phases, job.transitions, **options).fit(pairs, max_iter=job.max_iter, tol=job.tol,
                                                                seed=job.seed, progress=_say)
    sources = [str(p.resolve()) for p in job.files]
    model.metadata["demonstrations"] = sources
    out = job.out
    task = None
    if model.n_state in STATES.values() and model.n_force in FEATURES.values():
        # the same learned task the scenario runner makes: a scenario's `model:` can reproduce it
        try:
            task = learn_task(model, demos, job.dt, selection=model.metadata.get("selection"), sources=sources,
                              source=str(out))
        except TaskError as exc:
            _say(f"etar learn: warning: no task to reproduce ({exc}); writing the model alone")
        if task is not None:
            task.save(out)
            matched = ", phases matched to the demonstrations' true labels" if task.phase_to_truth else ""
            _say(f"task: goal {np.round(task.goal, 3).tolist()}, impedance for "
                 f"{sum(i is not None for i in task.impedances)} of {task.n_phases} phases{matched}")
    else:
        _say(f"etar learn: a state of {model.n_state} and a force of {model.n_force} columns is no position/pose "
             f"task: writing the model alone")
    if task is None:
        out.parent.mkdir(parents=True, exist_ok=True)
        model.save(out)
    r = model.fit_report_
    _say(f"wrote {out}: {model.n_phases} phases, log-likelihood {r.log_likelihood:.2f}, "
         f"{r.n_iter} EM iterations, {r.seconds:.1f} s")
    return 0


# --------------------------------------------------------------------------
# inspect
# --------------------------------------------------------------------------


def state_units(model) -> tuple[str, str]:
    """(the units of the state, of its squares) as the model's metadata names them."""
    state = model.metadata.get("state")
    if state == "position" and model.n_state == STATES["position"]:
        return "m", "m²"
    if state == "pose" and model.n_state == STATES["pose"]:
        return ("m for the position columns, rad for the rotation vector's",
                "m² for the position columns plus rad² for the rotation vector's")
    return "units of the state columns", "squared units of the state columns"


def check_inspect(args):
    from etar.model import ETAR

    model = ETAR.load(args.model)  # a ValueError naming the file and the field
    if model.metadata.get("impedance"):  # with its task: printed only if the nodes would take it
        from etar.task import LearnedTask
        LearnedTask.from_model(model, args.model)
    loaded = []
    if args.demos:
        loaded = _load(_check_files(args.demos, "--demos"))
        _checked_arrays(loaded, model.n_state, model.n_force, like=f"the model {args.model}")
    return model, loaded


def inspect(model_path: str, model, loaded) -> int:
    from etar.analysis import prediction_errors
    from etar.metrics import score_demonstrations

    K, n, m = model.n_phases, model.n_state, model.n_force
    units, squared = state_units(model)
    print(f"{model_path}: {'ETAR' if model.transitions == 'effect' else 'STAR'} model, "
          f"{K} phases, state n={n}, force m={m}, {model.n_free_parameters} free parameters")
    fit = model.to_dict().get("fit")
    if fit:
        print(f"fit: log-likelihood {fit['log_likelihood']:.2f} over {fit['n_samples']} steps, "
              f"{fit['n_iter']} iterations, {'converged' if fit['converged'] else 'not converged'}, seed {fit['seed']}")
    sel = model.metadata.get("selection")
    if sel:
        per_demo = sel.get("per_demonstration", [])
        print(f"\nnumber of phases chosen by {sel['criterion'].upper()}: {sel['best']}"
              f"{' (each demonstration chose; the majority won)' if per_demo else ''}")
        for i, d in enumerate(per_demo):
            print(f"  demonstration {i}: " + ", ".join(
                f"K={k} {d['scores'][k]:.1f}" for k in sorted(d["scores"], key=int)) + f"  -> {d['best']}")
        for k in sorted(sel.get("scores", {}), key=int):
            mark = "  <- best" if int(k) == sel["best"] else ""
            print(f"  K={k}: {sel['criterion'].upper()} {sel['scores'][k]:.2f}  "
                  f"(log-lik {sel['log_likelihoods'][k]:.2f}, {sel['n_parameters'][k]} params){mark}")
    np.set_printoptions(precision=4, suppress=False, linewidth=120)
    for j in range(K):
        std = np.sqrt(np.diag(model.Sigma[j]))
        print(f"\nphase {j}:")
        print("  A =\n" + textwrap.indent(np.array2string(model.A[j]), "    "))
        print("  B (force columns, then intercept) =\n" + textwrap.indent(np.array2string(model.B[j]), "    "))
        print(f"  noise std per state dimension ({units}) = {std}")
        imp = (model.metadata.get("impedance") or [None] * K)[j]
        if imp:
            print(f"  impedance: direction {np.round(imp['direction'], 3).tolist()}, "
                  f"{imp['n_compliant']} compliant axis/axes {np.round(imp['compliant_axes'], 3).tolist()}, "
                  f"mean force {np.round(imp['mean_force'], 2).tolist()} N")
    if loaded:
        demos = [d for _, d in loaded]
        pairs = [(d["states"], d["forces"]) for d in demos]
        print(f"\none-step prediction error (mean over steps of the squared error summed over the state columns, "
              f"{squared}), rows: Viterbi phases")
        print(prediction_errors(model, pairs).table())
        paths = [model.viterbi(s, f) for s, f in pairs]
        for (p, _), path in zip(loaded, paths):
            sw = np.flatnonzero(np.diff(path)) + 1
            print(f"{p}: phases {np.unique(path).tolist()}, switches at steps {sw.tolist()}")
        if all("phases" in d for d in demos):
            overall, _ = score_demonstrations([d["phases"] for d in demos], paths,
                                              float(demos[0].get("dt", 1.0)), n_pred=K)
            print(f"against ground truth: accuracy {overall.accuracy:.4f}, mean transition error "
                  f"{overall.mean_transition_error:.4f} s, spurious switches {overall.spurious_switches}")
    return 0


# --------------------------------------------------------------------------
# synth
# --------------------------------------------------------------------------


SYNTH_DT = 0.01  # s between the synthetic samples
# a learner needs a handful of demonstrations of a few hundred samples: past these a typo fills the disk
SYNTH_MAX_DEMOS, SYNTH_MAX_LENGTH = 1000, 100_000


@dataclass(frozen=True)
class SynthJob:
    out: Path
    demos: int
    length: int
    phases: int
    seed: int


def check_synth(args) -> SynthJob:
    phases = _at_least("--phases", args.phases, 1, high=MAX_PHASES)
    demos = _at_least("--demos", args.demos, 1, high=SYNTH_MAX_DEMOS)
    length = _at_least("--length", args.length, phases + 1,
                       f" (a sample more than one step per phase of --phases {phases})", SYNTH_MAX_LENGTH)
    seed = _at_least("--seed", args.seed, 0)
    return SynthJob(out=_out_folder("--out", args.out), demos=demos, length=length, phases=phases, seed=seed)


def synth(job: SynthJob) -> int:
    from etar.synthetic import make_task, sample_demonstrations

    task = make_task(job.phases, seed=job.seed)
    job.out.mkdir(parents=True, exist_ok=True)
    for i, (s, f, p) in enumerate(sample_demonstrations(task, job.demos, job.length, seed=job.seed + 1)):
        path = job.out / f"demo_{i:02d}.npz"
        np.savez(path, states=s, forces=f, phases=p, dt=np.float64(SYNTH_DT))
        _say(f"wrote {path} ({s.shape[0]} samples)")
    return 0


# --------------------------------------------------------------------------
# the command line
# --------------------------------------------------------------------------


def _learn_command(args):
    job = check_learn(args)
    _warn("learn", job.loaded)
    return lambda: learn(job)


def _inspect_command(args):
    model, loaded = check_inspect(args)
    _warn("inspect", loaded)
    return lambda: inspect(args.model, model, loaded)


def _synth_command(args):
    job = check_synth(args)
    return lambda: synth(job)


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(prog="etar", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"etar {_version()}",
                        help="print the installed version and exit")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("learn", help="fit an ETAR model to demonstrations")
    p.add_argument("demos", nargs="+", metavar="DEMOS",
                   help="demonstration files: .npz (arrays states (T, n), forces (T, m), optional phases, dt in s) "
                        "or .mcap demonstration recordings")
    p.add_argument("--phases", default="auto",
                   help=f"number of phases, an integer in 1..{MAX_PHASES}, or 'auto' to choose it by --criterion "
                        "(default auto)")
    p.add_argument("--max-phases", type=int, default=6,
                   help=f"largest candidate for --phases auto, 1..{MAX_PHASES}; the candidates are 1..this "
                        "(default %(default)s)")
    p.add_argument("--criterion", choices=CRITERIA, default="bic",
                   help="how --phases auto scores a candidate number of phases: bic (Bayesian) or aic (Akaike) "
                        "information criterion, the lowest wins (default %(default)s)")
    p.add_argument("--selection", choices=("per_demonstration", "pooled"), default="per_demonstration",
                   help="per_demonstration: each demonstration chooses its number of phases and the majority "
                        "wins (thesis 6.1); pooled: one score over all demonstrations (default %(default)s)")
    p.add_argument("--transitions", choices=TRANSITIONS, default="effect",
                   help="effect: ETAR (force features); state: STAR (position relative to the end point) "
                        "(default %(default)s)")
    p.add_argument("--out", required=True, metavar="FILE",
                   help="model file to write (JSON); its folder is created, an existing file replaced")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the restarts' random initial segmentations, >= 0; the same seed gives the same "
                        "model (default %(default)s)")
    p.add_argument("--restarts", type=int, default=4,
                   help="segment-based initialisations, >= 1, each run for 15 EM iterations; the best one "
                        "continues (default %(default)s)")
    p.add_argument("--max-iter", type=int, default=200,
                   help="EM iterations of the best restart after its 15, >= 1 (with --restarts 1: of the one run) "
                        "(default %(default)s)")
    p.add_argument("--tol", type=float, default=1e-7,
                   help="EM stops when the objective gains less than this, in nats per sample per iteration, "
                        "averaged over 10 iterations; > 0 (default %(default)s)")
    p.add_argument("--solver", choices=("gd", "lbfgs"), default="gd",
                   help="M-step solver for the transition weights W (default %(default)s)")
    p.add_argument("--dt", type=float, default=None,
                   help="sample period in s, > 0 (default: the first file's dt, else 0.01)")
    p.set_defaults(command_of=_learn_command)

    p = sub.add_parser("inspect", help="print a model's parameters, BIC table and impedances")
    p.add_argument("model", metavar="MODEL", help="model file to read (JSON, from etar learn or a run's learn stage)")
    p.add_argument("--demos", nargs="*", default=[], metavar="DEMO",
                   help="also segment these demonstration files (.npz or .mcap) and score the model on them")
    p.set_defaults(command_of=_inspect_command)

    p = sub.add_parser("synth", help="write synthetic demonstrations drawn from a known model")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="folder to write demo_XX.npz into (created; existing demo_XX.npz are replaced)")
    p.add_argument("--demos", type=int, default=6,
                   help=f"number of demonstrations, 1..{SYNTH_MAX_DEMOS} (a learner needs a handful; more only fill "
                        "the folder) (default %(default)s)")
    p.add_argument("--length", type=int, default=600,
                   help=f"samples per demonstration, {SYNTH_DT * 1000:g} ms apart, >= --phases + 1 and <= "
                        f"{SYNTH_MAX_LENGTH} (default %(default)s)")
    p.add_argument("--phases", type=int, default=3,
                   help=f"number of phases of the true model, 1..{MAX_PHASES} (default %(default)s)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the true model, >= 0; the demonstrations are drawn with seed + 1 "
                        "(default %(default)s)")
    p.set_defaults(command_of=_synth_command)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    name = f"etar {args.command}"
    try:
        run = args.command_of(args)  # every flag and file checked; nothing done yet
    except (ValueError, OSError) as exc:  # UsageError, DemonstrationError, a model file's ValueError
        print(f"{name}: error: {one_line(exc)}", file=sys.stderr)
        return USAGE_ERROR
    try:
        return run()
    except BrokenPipeError:
        return reader_gone()
    except (ValueError, OSError, FloatingPointError) as exc:
        print(f"{name}: error: {one_line(exc)}", file=sys.stderr)
        return RUN_FAILED
    except (KeyboardInterrupt, SystemError) as exc:
        if interrupt_behind(exc) is None:  # a SystemError that is no Ctrl-C inside compiled code
            raise
        print(f"{name}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
