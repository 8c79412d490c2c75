"""ETAR against STAR on the same demonstrations (thesis 6.3), offline.

The thesis' claim: phase transitions driven by the effect of the action (the
measured force, ETAR) are smoother and more accurate than transitions driven by
the state (the tool's position relative to the goal, STAR), and STAR's
predictions are worse at the transitions.  ``evaluate`` scores one fitted model
against the true phases: the Viterbi segmentation and the online filter's
most likely phase (what a reproduction acts on), each as accuracy after
Hungarian matching, transition-time error and spurious switches; and the
one-step prediction error of the parameters of the filter's phase, near the
true transitions and away from them.  ``compare_transitions`` fits both
transition models on the same data over several seeds and evaluates each.
Pure functions over arrays; nothing here reads files.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from etar.metrics import SegmentationScore, score_demonstrations
from etar.model import ETAR

NEAR_TRANSITION_STEPS = 5  # a step within this many of a true transition is "at" it
MODEL_NAMES = {"effect": "ETAR", "state": "STAR"}  # the thesis' names of the two transition models


def spread(values) -> dict | None:
    """Mean, min, max and count of the finite ones among ``values`` (None counts as
    missing); None if there is none."""
    a = np.asarray([v for v in values if v is not None], dtype=np.float64)
    a = a[np.isfinite(a)]
    if not len(a):
        return None
    return {"mean": float(a.mean()), "min": float(a.min()), "max": float(a.max()), "n": int(len(a))}


@dataclass(frozen=True)
class Evaluation:
    transitions: str  # "effect" (ETAR) or "state" (STAR)
    seed: int
    log_likelihood: float
    viterbi: SegmentationScore
    filtered: SegmentationScore
    error_near_transitions: float  # mean squared one-step error, filter's phase's parameters, [state units^2]
    error_elsewhere: float
    filtered_labels: tuple = ()  # the filter's phase of every step, per demonstration (not in to_dict)

    def to_dict(self) -> dict:
        return {"transitions": self.transitions, "seed": self.seed, "log_likelihood": self.log_likelihood,
                "viterbi": self.viterbi.to_dict(), "filtered": self.filtered.to_dict(),
                "error_near_transitions": self.error_near_transitions, "error_elsewhere": self.error_elsewhere}


def filtered_messages(model: ETAR, states, forces) -> np.ndarray:
    """(T-1, K) the online filter's normalised forward message of every step: the phase
    of step t -> t+1 is known once sample t+1 has come."""
    filt = model.filter()
    filt.update(states[0], forces[0])
    return np.array([filt.update(states[t], forces[t]) for t in range(1, len(states))])


def filtered_phases(model: ETAR, states, forces) -> np.ndarray:
    """(T-1,) the online filter's most likely phase of every step."""
    return np.argmax(filtered_messages(model, states, forces), axis=1).astype(np.int64)


def prediction_error_by_label(model: ETAR, states, forces, labels) -> np.ndarray:
    """(T-1,) squared one-step error of predicting s_{t+1} with the parameters of
    ``labels[t]``'s phase (thesis eq. 80-81)."""
    A, B = np.asarray(model.A), np.asarray(model.B)
    u = np.hstack([forces[:-1], np.ones((len(states) - 1, 1))])
    lab = np.asarray(labels, dtype=np.int64)
    pred = np.einsum("tij,tj->ti", A[lab], states[:-1]) + np.einsum("tij,tj->ti", B[lab], u)
    return ((pred - states[1:]) ** 2).sum(axis=1)


def near_transitions(truth, steps: int = NEAR_TRANSITION_STEPS) -> np.ndarray:
    """(T-1,) bool: within ``steps`` of a change of the true phase."""
    truth = np.asarray(truth)
    near = np.zeros(truth.shape, dtype=bool)
    for b in np.flatnonzero(np.diff(truth)) + 1:
        near[max(0, b - steps):b + steps] = True
    return near


def evaluate(model: ETAR, demos: Sequence, truths: Sequence, dt: float, seed: int = 0,
             n_true: int | None = None) -> Evaluation:
    """Score a fitted model against the true phases of ``demos`` (see the module doc)."""
    demos = [(np.asarray(s, dtype=np.float64), np.asarray(f, dtype=np.float64)) for s, f in demos]
    truths = [np.asarray(t, dtype=np.int64) for t in truths]
    for i, ((s, _), t) in enumerate(zip(demos, truths)):
        if t.shape != (len(s) - 1,):
            raise ValueError(f"truths[{i}] must have one phase per step ({len(s) - 1}), got {t.shape}")
    vit = [model.viterbi(s, f) for s, f in demos]
    filt = [filtered_phases(model, s, f) for s, f in demos]
    K = model.n_phases
    v_score, _ = score_demonstrations(truths, vit, dt, n_true, K)
    f_score, _ = score_demonstrations(truths, filt, dt, n_true, K)
    err = np.concatenate([prediction_error_by_label(model, s, f, lab) for (s, f), lab in zip(demos, filt)])
    near = np.concatenate([near_transitions(t) for t in truths])
    return Evaluation(model.transitions, seed, float(model.log_likelihood(demos)), v_score, f_score,
                      float(err[near].mean()) if near.any() else float("nan"),
                      float(err[~near].mean()) if (~near).any() else float("nan"), tuple(filt))


def compare_transitions(demos: Sequence, truths: Sequence, n_phases: int, dt: float, seeds=(0, 1, 2),
                        max_iter: int = 200, n_restarts: int = 4, progress=None) -> list[Evaluation]:
    """Fit ETAR and STAR with ``n_phases`` on the same demonstrations, once per seed, and
    evaluate each against the truth: [effect seed 0, state seed 0, effect seed 1, ...]."""
    out = []
    for seed in seeds:
        for transitions in ("effect", "state"):
            model = ETAR(n_phases, transitions, n_restarts=n_restarts).fit(demos, max_iter=max_iter, seed=int(seed))
            out.append(evaluate(model, demos, truths, dt, int(seed)))
            if progress is not None:
                e = out[-1]
                progress(f"{'ETAR' if transitions == 'effect' else 'STAR'} seed {seed}: filter accuracy "
                         f"{e.filtered.accuracy:.3f}, Viterbi {e.viterbi.accuracy:.3f}")
    return out


def summarise(evaluations: Sequence[Evaluation]) -> dict:
    """Per transition model: mean and spread over the seeds of each figure."""
    out = {}
    for transitions in ("effect", "state"):
        es = [e for e in evaluations if e.transitions == transitions]
        if not es:
            continue
        out[MODEL_NAMES[transitions]] = {
            "seeds": [e.seed for e in es],
            "viterbi_accuracy": spread([e.viterbi.accuracy for e in es]),
            "filter_accuracy": spread([e.filtered.accuracy for e in es]),
            "filter_mean_transition_error_s": spread([e.filtered.mean_transition_error for e in es]),
            "filter_spurious_switches": spread([e.filtered.spurious_switches for e in es]),
            "filter_missed_transitions": spread([e.filtered.missed_transitions for e in es]),
            "error_near_transitions": spread([e.error_near_transitions for e in es]),
            "error_elsewhere": spread([e.error_elsewhere for e in es]),
        }
    return out


# --- Table C1: the parameters of two similar demonstrations learned separately ----------

PARAMETERS = ("A", "B", "Sigma", "W")


def _relative(x: np.ndarray, y: np.ndarray) -> float:
    """||x - y|| / mean(||x||, ||y||) (Frobenius): 0 the same, 2 opposite."""
    scale = 0.5 * (np.linalg.norm(x) + np.linalg.norm(y))
    return float(np.linalg.norm(x - y) / scale) if scale > 0 else 0.0


def gauge_free_weights(W: np.ndarray) -> np.ndarray:
    """The softmax weights with each row's mean over the destination phases removed: adding
    one vector to every destination's weights changes no probability, so only this part
    can be compared between two fits."""
    W = np.asarray(W, dtype=np.float64)
    return W - W.mean(axis=1, keepdims=True)


def permuted(model: ETAR, perm) -> dict:
    """``model``'s parameters with its phase ``perm[i]`` as phase i (W on both of its axes)."""
    p = np.asarray(perm, dtype=np.int64)
    W = np.asarray(model.W, dtype=np.float64)
    W = np.concatenate([W[:1], W[1:][p]], axis=0)[:, p]
    return {"A": np.asarray(model.A)[p], "B": np.asarray(model.B)[p], "Sigma": np.asarray(model.Sigma)[p],
            "W": gauge_free_weights(W)}


def match_by_parameters(a: ETAR, b: ETAR) -> np.ndarray:
    """(K,) ``b``'s phase matched to each of ``a``'s (Hungarian) by the summed relative
    distances of their A, B and Sigma: the phases of two separate fits come in any order
    (thesis Table C1 shows them permuted).  Each parameter is weighed relative to its own
    size: A is near the identity in every phase, so in one block [A | B] the phases' B
    (what tells them apart) would hardly count."""
    from scipy.optimize import linear_sum_assignment

    K = a.n_phases
    if b.n_phases != K:
        raise ValueError(f"the two models have {K} and {b.n_phases} phases: they cannot be matched one to one")
    pa, pb = permuted(a, np.arange(K)), permuted(b, np.arange(K))
    cost = np.array([[sum(_relative(pa[k][i], pb[k][j]) for k in ("A", "B", "Sigma")) for j in range(K)]
                     for i in range(K)])
    rows, cols = linear_sum_assignment(cost)
    return cols[np.argsort(rows)]


def parameter_distances(a: ETAR, b: ETAR, perm=None) -> dict:
    """Relative distance of each parameter (``PARAMETERS``) after matching ``b``'s phases to
    ``a``'s (``perm``; default by `match_by_parameters`), and the permutation used."""
    perm = match_by_parameters(a, b) if perm is None else np.asarray(perm, dtype=np.int64)
    pa, pb = permuted(a, np.arange(a.n_phases)), permuted(b, perm)
    return {"permutation": [int(x) for x in perm], **{k: _relative(pa[k], pb[k]) for k in PARAMETERS}}


def truth_permutation(a: ETAR, b: ETAR, demo_a, truth_a, demo_b, truth_b) -> list[int] | None:
    """The matching the true phases give (each fit's Viterbi phases mapped to the truth),
    or None where a fit leaves a true phase without a phase of its own."""
    from etar.metrics import match_phases

    ma = match_phases(np.asarray(truth_a), a.viterbi(*demo_a), None, a.n_phases)
    mb = match_phases(np.asarray(truth_b), b.viterbi(*demo_b), None, b.n_phases)
    to_b = {true: phase for phase, true in mb.items()}
    if len(set(ma.values())) < a.n_phases or len(to_b) < b.n_phases:
        return None
    return [int(to_b[ma[i]]) for i in range(a.n_phases)]


def separate_fits(demo_a, demo_b, n_phases: int, seeds=(0, 1, 2), truths=None, transitions: str = "effect",
                  max_iter: int = 200, n_restarts: int = 4, progress=None) -> dict:
    """Table C1's check: each demonstration fitted on its own with every seed; the
    parameter distance between the two demonstrations' fits (same seed), beside the
    distance between two seeds' fits of one demonstration (how far EM alone lands apart).

    ``truths``: the two demonstrations' true phases, to say whether matching by the
    parameters agrees with matching by the truth."""
    fits = {}
    for which, demo in (("a", demo_a), ("b", demo_b)):
        for seed in seeds:
            fits[which, seed] = ETAR(n_phases, transitions, n_restarts=n_restarts).fit([demo], max_iter=max_iter,
                                                                                     seed=int(seed))
            if progress is not None:
                progress(f"Table C1: demonstration {which}, seed {seed} fitted")
    between = [dict(seed=int(s), **parameter_distances(fits["a", s], fits["b", s])) for s in seeds]
    if truths is not None:
        for row, s in zip(between, seeds):
            row["truth_permutation"] = truth_permutation(fits["a", s], fits["b", s], demo_a, truths[0], demo_b,
                                                         truths[1])
            row["matching_agrees_with_truth"] = row["truth_permutation"] == row["permutation"]
    within = [dict(demonstration=w, seeds=[int(seeds[0]), int(s)], **parameter_distances(fits[w, seeds[0]], fits[w, s]))
              for w in ("a", "b") for s in seeds[1:]]

    return {"phases": n_phases, "seeds": [int(s) for s in seeds],
            "between_demonstrations": between, "between_seeds": within,
            "summary": {k: {"between_demonstrations": spread(r[k] for r in between),
                            "between_seeds": spread(r[k] for r in within)} for k in PARAMETERS},
            "models": {f"{w}_seed{s}": fits[w, s] for (w, s) in fits}}
