"""Does EM find the best model of the two-sided valley?  (thesis 6.2)

For each folder of recorded demonstrations (a run or a sweep's run with ``--record
full``), pooled over its demonstrations:

* the K-phase models EM finds from its own starts (the learn stage's: 4 restarts,
  200 iterations, the run's seed), K = 1..6, with their log-likelihood and BIC;
* the K-phase model EM reaches from the true segmentation (``ETAR.fit(start_labels=
  true phases)``), K = the number of true phases, and its log-likelihood and BIC;
* how each of the two K-phase models segments the demonstrations (Viterbi) against
  the true phases, per side (phases matched to true ones on all demonstrations);
* what the data look like per side and true phase: samples, force along the
  plate's normal and its size, speed.

    python bench/true_segmentation.py runs/two/runs/run000 runs/two/runs/run001 ...

Demonstrations of one seed: ``etar-bench sweep SCENARIO --param seed=0,1,2,3,4 --record
full --out DIR`` with a scenario that only demonstrates (valley_two_sides.yaml's first
stage).  Prints a table per folder and a summary over them; ``--json FILE`` keeps it all.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

CANDIDATES = (1, 2, 3, 4, 5, 6)
PHASE_NAMES = {0: "free", 1: "plate", 2: "groove"}


def study(folder: str, subset: tuple | None = None) -> dict:
    import yaml

    from etar import ETAR
    from etar.metrics import match_phases
    from etar.selection import information_criterion
    from services.recordings.demonstrations import load_demonstration

    folder = Path(folder)
    report = json.loads((folder / "report.json").read_text())
    seed = int(yaml.safe_load((folder / "scenario.yaml").read_text()).get("seed", 0))
    demos, sides = [], []
    for i, d in enumerate(report["demonstrations"]):
        if subset is not None and i not in subset:
            continue
        rec = load_demonstration(folder / d["path"])
        demos.append(rec)
        sides.append(d["side"])
    pairs = [(d["states"], d["forces"]) for d in demos]
    truth_steps = [np.asarray(d["phases"], dtype=np.int64) for d in demos]
    K_true = int(max(z.max() for z in truth_steps)) + 1
    n, m = pairs[0][0].shape[1], pairs[0][1].shape[1]
    n_steps = sum(len(z) for z in truth_steps)

    def scored(model) -> dict:
        ll = float(model.log_likelihood(pairs))
        p = ETAR.count_free_parameters(model.n_phases, n, m, m)
        return dict(log_likelihood=ll, n_parameters=p, bic=information_criterion(ll, p, n_steps, "bic"))

    def segmentation(model) -> dict:
        paths = [model.viterbi(s, f) for s, f in pairs]
        mapping = match_phases(np.concatenate(truth_steps), np.concatenate(paths), K_true, model.n_phases)
        per_side = {}
        for side in sorted(set(sides)):
            z = np.concatenate([t for t, s in zip(truth_steps, sides) if s == side])
            est = np.concatenate([p for p, s in zip(paths, sides) if s == side])
            mapped = np.array([mapping.get(int(k), -1) for k in est])
            confusion = np.zeros((K_true, model.n_phases), dtype=np.int64)
            np.add.at(confusion, (z, est), 1)
            per_side[side] = dict(accuracy=float(np.mean(mapped == z)), confusion=confusion.tolist())
        return dict(mapping={int(k): int(v) for k, v in mapping.items()}, per_side=per_side)

    em_models = {k: ETAR(k, n_restarts=4).fit(pairs, max_iter=200, seed=seed) for k in CANDIDATES}
    em_scores = {k: scored(mo) for k, mo in em_models.items()}
    bic_choice = min(em_scores, key=lambda k: em_scores[k]["bic"])
    from_truth = ETAR(K_true, n_restarts=4).fit(pairs, max_iter=200, seed=seed, start_labels=truth_steps)

    # the data per side and true phase: the force along the plate's normal (base y,z:
    # the plates are 45 degrees, mirror images across the valley's middle y = 0)
    data = {}
    for side in sorted(set(sides)):
        for ph in range(K_true):
            f, v = [], []
            for d, s, z in zip(demos, sides, truth_steps):
                if s != side:
                    continue
                at = np.flatnonzero(z == ph)  # step t -> t+1 of phase z[t]
                f.append(d["forces"][at + 1])
                v.append(np.linalg.norm(np.diff(d["states"], axis=0)[at], axis=1) / float(d["dt"]))
            if not f:
                continue
            f, v = np.concatenate(f), np.concatenate(v)
            data[f"{side} {PHASE_NAMES.get(ph, ph)}"] = dict(
                samples=int(len(v)), force_norm_N=float(np.median(np.linalg.norm(f, axis=1))),
                force_mean_N=[float(x) for x in f.mean(axis=0)], speed_mm_s=float(1e3 * np.median(v)))
    # where the two models' likelihoods differ: each step's expected log-emission under
    # the smoothed posterior, summed per side and true phase
    def emission_fit(model) -> dict:
        out = {}
        for (s, f), z, side in zip(pairs, truth_steps, sides):
            _, _, _, log_emis = model._inference_arrays(s, f)
            per_step = (model.posterior(s, f) * log_emis).sum(axis=1)
            for ph in range(K_true):
                key = f"{side} {PHASE_NAMES.get(ph, ph)}"
                out[key] = out.get(key, 0.0) + float(per_step[z == ph].sum())
        return out

    # what sharing one linear AR phase costs: one model fitted to the steps of two
    # stretches (side, true phase) together, against one fitted to each (log-likelihood
    # lost); "mirrored": the second stretch reflected across the valley's middle (y -> -y
    # in state and force), so only the demonstrations' differences remain, not the geometry
    def stretch(side, ph, mirror=False):
        out = []
        for (st, f), z, sd in zip(pairs, truth_steps, sides):
            if sd != side:
                continue
            at = np.flatnonzero(z == ph)
            for run in np.split(at, np.flatnonzero(np.diff(at) > 1) + 1):
                if len(run) >= 5:
                    a, b = run[0], run[-1] + 2  # the steps' samples
                    s2, f2 = st[a:b].copy(), f[a:b].copy()
                    if mirror:
                        s2[:, 1] *= -1.0
                        f2[:, 1] *= -1.0
                    out.append((s2, f2))
        return out

    def one_phase(segments) -> float:
        return float(ETAR(1, n_restarts=1).fit(segments, max_iter=20, seed=seed).log_likelihood(segments))

    sharing = {}
    if set(sides) == {"left", "right"} and K_true == 3:
        alone = {(sd, ph): one_phase(stretch(sd, ph)) for sd in ("left", "right") for ph in range(3)}
        pairs_to_share = {"left plate + right plate": (("left", 1), ("right", 1)),
                          "left free + right free": (("left", 0), ("right", 0)),
                          "left free + left plate": (("left", 0), ("left", 1)),
                          "right free + right plate": (("right", 0), ("right", 1)),
                          "left free + right plate": (("left", 0), ("right", 1)),
                          "right free + left plate": (("right", 0), ("left", 1))}
        for name, (x, y) in pairs_to_share.items():
            both = one_phase(stretch(*x) + stretch(*y))
            entry = {"cost": alone[x] + alone[y] - both}
            if x[0] != y[0]:
                entry["cost_mirrored"] = alone[x] + alone[y] - one_phase(stretch(*x) + stretch(*y, mirror=True))
            sharing[name] = entry

    # which terms one law for both plates must give up: least squares of each axis of
    # s_{t+1} on [s_t, f_t, 1] over both plates' steps, the right plate mirrored onto the
    # left; a law that serves both plates unmirrored commutes with the mirror, so its
    # terms coupling y with x or z (and b_y) are zero.  Log-likelihood lost (Gaussian,
    # each axis alone) when they are.
    mirror_terms = {}
    if set(sides) == {"left", "right"} and K_true == 3:
        X, Y = [], []
        for (st, f), z, sd in zip(pairs, truth_steps, sides):
            M = np.array([1.0, -1.0, 1.0]) if sd == "right" else np.ones(3)
            at = np.flatnonzero(z == 1)
            X.append(np.hstack([st[at] * M, f[at] * M, np.ones((len(at), 1))]))
            Y.append(st[at + 1] * M)
        X, Y = np.vstack(X), np.vstack(Y)
        odd = np.array([[(o == 1) != (j % 3 == 1) if j < 6 else o == 1 for j in range(7)] for o in range(3)])

        def half_n_log_variance(o, zero_terms) -> float:
            coef, *_ = np.linalg.lstsq(X[:, ~zero_terms], Y[:, o], rcond=None)
            r = Y[:, o] - X[:, ~zero_terms] @ coef
            return len(r) / 2 * np.log(r @ r / len(r))

        def lost(zero) -> float:
            return sum(half_n_log_variance(o, zero[o]) - half_n_log_variance(o, np.zeros(7, bool)) for o in range(3))

        def only(rows=slice(None), cols=slice(None)):
            zero = np.zeros_like(odd)
            zero[rows, cols] = odd[rows, cols]
            return zero

        mirror_terms = {"all": lost(odd), "A (state)": lost(only(cols=slice(0, 3))),
                        "B (force)": lost(only(cols=slice(3, 6))), "b (constant)": lost(only(cols=slice(6, 7))),
                        **{f"axis {a}": lost(only(rows=slice(i, i + 1))) for i, a in enumerate("xyz")}}

    fit_own, fit_truth = emission_fit(em_models[K_true]), emission_fit(from_truth)
    for key in data:
        data[key]["emission_own_starts"] = fit_own.get(key, 0.0)
        data[key]["emission_from_truth"] = fit_truth.get(key, 0.0)
    return dict(folder=str(folder), seed=seed, sides=sides, n_steps=n_steps, true_phases=K_true, sharing=sharing, mirror_terms=mirror_terms,
                em={k: dict(em_scores[k], objective=mo.fit_report_.objective) for k, mo in em_models.items()},
                em_segmentation=segmentation(em_models[K_true]),
                one_more_segmentation=segmentation(em_models[K_true + 1]) if K_true + 1 in em_models else None,
                bic_choice_segmentation=segmentation(em_models[bic_choice]),
                from_truth=dict(scored(from_truth), objective=from_truth.fit_report_.objective,
                                n_iter=from_truth.fit_report_.n_iter),
                from_truth_segmentation=segmentation(from_truth), data=data)


def show(r: dict) -> None:
    K = r["true_phases"]
    print(f"\n{r['folder']} (seed {r['seed']}; {len(r['sides'])} demonstrations, {r['n_steps']} steps)")
    print(f"  {'model':<22} {'log-lik':>11} {'params':>6} {'BIC':>11}")
    for k, s in r["em"].items():
        print(f"  EM, own starts, K={k:<4} {s['log_likelihood']:>11.1f} {s['n_parameters']:>6} {s['bic']:>11.1f}")
    t = r["from_truth"]
    print(f"  EM from truth, K={K:<5} {t['log_likelihood']:>11.1f} {t['n_parameters']:>6} {t['bic']:>11.1f}")
    best = min(r["em"], key=lambda k: r["em"][k]["bic"])
    print(f"  pooled BIC chooses K={best}; from truth minus own starts at K={K}: "
          f"log-lik {t['log_likelihood'] - r['em'][K]['log_likelihood']:+.1f}")
    for k, name, seg in ((K, "own starts", r["em_segmentation"]), (K, "from truth", r["from_truth_segmentation"]),
                         (K + 1, "own starts", r["one_more_segmentation"]),
                         (best, "own starts (BIC's choice)", r["bic_choice_segmentation"])):
        if seg is None:
            continue
        sides = ", ".join(f"{s} {v['accuracy']:.3f}" for s, v in seg["per_side"].items())
        print(f"  K={k} {name}: Viterbi accuracy {sides}; confusion (true x learned):")
        for s, v in seg["per_side"].items():
            rows = "  ".join(f"{PHASE_NAMES.get(i, i)}:{row}" for i, row in enumerate(v["confusion"]))
            print(f"      {s:<5} {rows}")
    print(f"  {'data':<14} {'samples':>7} {'|f| median N':>13} {'mean f (x,y,z) N':>24} {'speed mm/s':>10} "
          f"{'emission log-lik: own starts':>28} {'from truth':>11} {'difference':>10}")
    for key, d in r["data"].items():
        mean = ", ".join(f"{x:6.1f}" for x in d["force_mean_N"])
        own, truth = d["emission_own_starts"], d["emission_from_truth"]
        print(f"  {key:<14} {d['samples']:>7} {d['force_norm_N']:>13.1f} {mean:>24} {d['speed_mm_s']:>10.1f} "
              f"{own:>28.1f} {truth:>11.1f} {truth - own:>+10.1f}")
    if r["sharing"]:
        print("  one AR phase for two stretches, log-likelihood lost against one phase each"
              " (mirrored: the second reflected y -> -y):")
        for name, e in r["sharing"].items():
            mirrored = f", mirrored {e['cost_mirrored']:8.1f}" if "cost_mirrored" in e else ""
            print(f"      {name:<26} {e['cost']:8.1f}{mirrored}")
    if r["mirror_terms"]:
        print("  one law for both plates, the terms it must give up (y coupled with x or z), log-likelihood lost "
              "(least squares per axis):")
        print("      " + ", ".join(f"{k} {v:.1f}" for k, v in r["mirror_terms"].items()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folders", nargs="+", help="run folders with recorded demonstrations (report.json beside)")
    ap.add_argument("--workers", type=int, default=2, help="folders studied at once (default 2)")
    ap.add_argument("--json", type=Path, help="write every number to this file")
    ap.add_argument("--demonstrations", metavar="I,J,...",
                    help="only these demonstrations of each folder, by index (e.g. 0,1: one per side, as the "
                         "thesis had)")
    args = ap.parse_args(argv)
    if args.workers < 1:
        ap.error(f"--workers: expected a count >= 1, got {args.workers}")
    if args.json and not args.json.parent.is_dir():
        ap.error(f"--json: {args.json.parent} is not a folder")
    subset = None
    if args.demonstrations:
        try:
            subset = tuple(int(i) for i in args.demonstrations.split(","))
        except ValueError:
            ap.error(f"--demonstrations: expected indices like 0,1, got {args.demonstrations!r}")
    for f in args.folders:
        try:
            count = len(json.loads((Path(f) / "report.json").read_text())["demonstrations"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            ap.error(f"{f}: no readable report.json with demonstrations (a run folder with recorded "
                     f"demonstrations?): {e}")
        if subset is not None and not all(0 <= i < count for i in subset):
            ap.error(f"--demonstrations: {args.demonstrations} in {f}, which has demonstrations 0..{count - 1}")
    results = []
    with ProcessPoolExecutor(args.workers) as pool:
        try:
            for r in pool.map(study, args.folders, [subset] * len(args.folders)):
                show(r)
                results.append(r)
        except Exception as e:  # a recording that does not read, a fit that fails: one line, not a traceback
            ap.exit(2, f"{ap.prog}: error: {type(e).__name__}: {e}\n")
    K = results[0]["true_phases"]
    gain = [r["from_truth"]["log_likelihood"] - r["em"][K]["log_likelihood"] for r in results]
    chosen = [min(r["em"], key=lambda k: r["em"][k]["bic"]) for r in results]
    print(f"\nover {len(results)} folders: pooled BIC chooses {chosen}; the model from the true segmentation "
          f"minus EM's own at K={K}, log-likelihood: {', '.join(f'{g:+.1f}' for g in gain)}")
    for name, key in (("own starts", "em_segmentation"), ("from truth", "from_truth_segmentation")):
        for side in results[0][key]["per_side"]:
            acc = [r[key]["per_side"][side]["accuracy"] for r in results]
            print(f"  K={K} {name}, {side}: Viterbi accuracy mean {np.mean(acc):.3f} "
                  f"(min {min(acc):.3f}, max {max(acc):.3f})")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
