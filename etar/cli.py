"""``etar``: learn ETAR models from demonstrations and inspect them.

    etar learn DEMOS... --phases auto|N --out MODEL
    etar inspect MODEL [--demos DEMOS...]
    etar synth --out DIR          (synthetic demonstrations for trying it out)

Demonstrations are ``.npz`` files with arrays ``states`` (T, n) and
``forces`` (T, m), optionally ``phases`` (T-1,) ground truth and ``dt`` (s).
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from pathlib import Path

import numpy as np

from etar.demonstrations import DemonstrationError


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def load_npz_demonstration(path) -> dict:
    """{'states', 'forces', optional 'phases', 'dt'} from one .npz file, or a
    ``DemonstrationError`` naming the file and the field at fault."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            out = {k: data[k] for k in data.files}
    except FileNotFoundError:
        raise DemonstrationError(f"{path}: no such file") from None
    except (OSError, ValueError) as exc:
        raise DemonstrationError(f"{path}: not a readable .npz file ({exc})") from None
    for key in ("states", "forces"):
        if key not in out:
            raise DemonstrationError(f"{path}: field '{key}' is missing (found: {sorted(out)})")
    return out


# suffix -> function(path) -> list of demonstration dicts; other layers register
# their formats here (services adds .mcap recordings) so etar stays format-agnostic
LOADERS = {".npz": lambda p: [load_npz_demonstration(p)]}


def load_demonstrations(paths) -> list[dict]:
    demos = []
    for p in paths:
        p = Path(p)
        loader = LOADERS.get(p.suffix)
        if loader is None:
            raise DemonstrationError(
                f"{p}: unsupported demonstration file type '{p.suffix}' (expected one of {sorted(LOADERS)})")
        demos.extend(loader(p))
    return demos


def _pairs(demos):
    return [(d["states"], d["forces"]) for d in demos]


def cmd_learn(args) -> int:
    from etar.model import ETAR
    from etar.selection import fit_order
    from etar.task import FEATURES, STATES, TaskError, learn_task

    demos = load_demonstrations(args.demos)
    pairs = _pairs(demos)
    options = dict(n_restarts=args.restarts, solver=args.solver)
    if args.phases == "auto":
        candidates = range(1, args.max_phases + 1)
        _say(f"selecting the number of phases by {args.criterion.upper()} over {list(candidates)} "
             f"from {len(pairs)} demonstration(s)")
        # with one demonstration, voting is the pooled choice and one more fit
        model, selection = fit_order(pairs, candidates, args.criterion, args.selection if len(pairs) > 1 else "pooled",
                                     transitions=args.transitions, seed=args.seed, max_iter=args.max_iter,
                                     tol=args.tol, progress=_say, **options)
        model.metadata["selection"] = selection
    else:
        try:
            k = int(args.phases)
        except ValueError:
            raise SystemExit(f"etar learn: --phases must be 'auto' or a positive integer, got {args.phases!r}")
        model = ETAR(k, args.transitions, **options).fit(pairs, max_iter=args.max_iter, tol=args.tol,
                                                        seed=args.seed, progress=_say)
    sources = [str(Path(p).resolve()) for p in args.demos]
    model.metadata["demonstrations"] = sources
    dt = args.dt if args.dt is not None else float(demos[0].get("dt", 0.01))
    out = Path(args.out).expanduser().resolve()
    task = None
    if model.n_state in STATES.values() and model.n_force in FEATURES.values():
        # the same learned task the scenario runner makes: a scenario's `model:` can reproduce it
        try:
            task = learn_task(model, demos, dt, selection=model.metadata.get("selection"), sources=sources,
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


def cmd_inspect(args) -> int:
    from etar.analysis import prediction_errors
    from etar.metrics import score_demonstrations
    from etar.model import ETAR

    model = ETAR.load(args.model)
    K, n, m = model.n_phases, model.n_state, model.n_force
    print(f"{args.model}: {'ETAR' if model.transitions == 'effect' else 'STAR'} model, "
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
        print(f"  noise std per state dimension = {std}")
        imp = (model.metadata.get("impedance") or [None] * K)[j]
        if imp:
            print(f"  impedance: direction {np.round(imp['direction'], 3).tolist()}, "
                  f"{imp['n_compliant']} compliant axis/axes {np.round(imp['compliant_axes'], 3).tolist()}, "
                  f"mean force {np.round(imp['mean_force'], 2).tolist()} N")
    if args.demos:
        demos = load_demonstrations(args.demos)
        pairs = _pairs(demos)
        print("\none-step prediction error (mean squared, state units^2), rows: Viterbi phases")
        print(prediction_errors(model, pairs).table())
        paths = [model.viterbi(s, f) for s, f in pairs]
        for p, path in zip(args.demos, paths):
            sw = np.flatnonzero(np.diff(path)) + 1
            print(f"{p}: phases {np.unique(path).tolist()}, switches at steps {sw.tolist()}")
        if all("phases" in d for d in demos):
            overall, _ = score_demonstrations([d["phases"] for d in demos], paths,
                                              float(demos[0].get("dt", 1.0)), n_pred=K)
            print(f"against ground truth: accuracy {overall.accuracy:.4f}, mean transition error "
                  f"{overall.mean_transition_error:.4f} s, spurious switches {overall.spurious_switches}")
    return 0


def cmd_synth(args) -> int:
    from etar.synthetic import make_task, sample_demonstrations

    task = make_task(args.phases, seed=args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for i, (s, f, p) in enumerate(sample_demonstrations(task, args.demos, args.length, seed=args.seed + 1)):
        path = out / f"demo_{i:02d}.npz"
        np.savez(path, states=s, forces=f, phases=p, dt=np.float64(0.01))
        _say(f"wrote {path} ({s.shape[0]} samples)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="etar", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("learn", help="fit an ETAR model to demonstrations")
    p.add_argument("demos", nargs="+", help="demonstration files (.npz with states, forces)")
    p.add_argument("--phases", default="auto", help="number of phases, or 'auto' to choose by --criterion")
    p.add_argument("--max-phases", type=int, default=6, help="largest candidate for --phases auto (default 6)")
    p.add_argument("--criterion", choices=("bic", "aic"), default="bic")
    p.add_argument("--selection", choices=("per_demonstration", "pooled"), default="per_demonstration",
                   help="per_demonstration: each demonstration chooses its number of phases and the majority "
                        "wins (thesis 6.1); pooled: one score over all demonstrations (default per_demonstration)")
    p.add_argument("--transitions", choices=("effect", "state"), default="effect",
                   help="effect: ETAR (force features); state: STAR (position relative to the end point)")
    p.add_argument("--out", required=True, help="model file to write (JSON)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--restarts", type=int, default=4, help="segment-based initialisations (default 4)")
    p.add_argument("--max-iter", type=int, default=200)
    p.add_argument("--tol", type=float, default=1e-7, help="EM stops below this gain per sample per iteration")
    p.add_argument("--solver", choices=("gd", "lbfgs"), default="gd", help="M-step solver for W")
    p.add_argument("--dt", type=float, default=None, help="sample period in s (default: from the files, else 0.01)")
    p.set_defaults(func=cmd_learn)

    p = sub.add_parser("inspect", help="print a model's parameters, BIC table and impedances")
    p.add_argument("model")
    p.add_argument("--demos", nargs="*", default=[], help="also segment these demonstrations")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("synth", help="write synthetic demonstrations drawn from a known model")
    p.add_argument("--out", required=True, help="directory to write demo_XX.npz into")
    p.add_argument("--demos", type=int, default=6)
    p.add_argument("--length", type=int, default=600)
    p.add_argument("--phases", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_synth)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (DemonstrationError, ValueError) as exc:
        print(f"etar {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
