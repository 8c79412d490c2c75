"""Choosing the number of phases by BIC or AIC (thesis 4.2)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

from etar.demonstrations import check_demonstrations
from etar.model import ETAR

CRITERIA = ("bic", "aic")


@dataclass(frozen=True)
class OrderSelection:
    """``best``: the chosen number of phases; ``scores``: candidate -> criterion
    (lower is better); the fitted model of every candidate is kept."""

    best: int
    criterion: str
    scores: dict
    log_likelihoods: dict
    n_parameters: dict
    n_samples: int
    models: dict

    @property
    def model(self) -> ETAR:
        return self.models[self.best]

    def table(self) -> str:
        """The scores as a small text table."""
        lines = [f"{'phases':>6} {'params':>7} {'log-lik':>14} {self.criterion.upper():>14}"]
        for k in sorted(self.scores):
            mark = "  <- best" if k == self.best else ""
            lines.append(
                f"{k:>6} {self.n_parameters[k]:>7} {self.log_likelihoods[k]:>14.2f} {self.scores[k]:>14.2f}{mark}"
            )
        return "\n".join(lines)


def information_criterion(log_likelihood: float, n_parameters: int, n_samples: int, criterion: str) -> float:
    """BIC = -2 log L + p log N; AIC = -2 log L + 2 p.

    N is the number of modelled steps (sum over demonstrations of T - 1): each
    step contributes one term s_{t+1} | s_t, f_t, phase to the likelihood.
    """
    if criterion == "bic":
        return -2.0 * log_likelihood + n_parameters * math.log(n_samples)
    if criterion == "aic":
        return -2.0 * log_likelihood + 2.0 * n_parameters
    raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")


def select_order(
    demos: Sequence,
    candidates: Sequence[int] = (1, 2, 3, 4, 5, 6),
    criterion: str = "bic",
    *,
    transitions: str = "effect",
    seed: int = 0,
    max_iter: int = 200,
    tol: float = 1e-7,
    progress: Callable[[str], None] | None = None,
    **model_options,
) -> OrderSelection:
    """Fit one model per candidate number of phases and score each.

    The parameter count is that of this model (``ETAR.count_free_parameters``),
    not of a plain Gaussian HMM.  Candidates with fewer steps than parameters
    are skipped (and reported through ``progress``); at least one must fit.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    candidates = sorted({int(k) for k in candidates})
    if not candidates or candidates[0] < 1:
        raise ValueError(f"candidates must be positive integers, got {candidates!r}")
    demos = check_demonstrations(demos)
    n, m = demos[0][0].shape[1], demos[0][1].shape[1]
    d = n if transitions == "state" else m
    n_samples = sum(s.shape[0] - 1 for s, _ in demos)
    scores, lls, params, models = {}, {}, {}, {}
    for k in candidates:
        p = ETAR.count_free_parameters(k, n, m, d)
        if p > n_samples:
            if progress:
                progress(f"K={k}: skipped, {p} parameters exceed {n_samples} steps")
            continue
        model = ETAR(k, transitions, **model_options).fit(demos, max_iter=max_iter, tol=tol, seed=seed)
        ll = model.fit_report_.log_likelihood
        scores[k] = information_criterion(ll, p, n_samples, criterion)
        lls[k], params[k], models[k] = ll, p, model
        if progress:
            progress(f"K={k}: log-likelihood {ll:.2f}, {p} parameters, {criterion.upper()} {scores[k]:.2f} "
                     f"({model.fit_report_.seconds:.1f} s)")
    if not scores:
        raise ValueError(f"no candidate in {candidates} has fewer parameters than the {n_samples} steps")
    best = min(scores, key=scores.get)
    return OrderSelection(best, criterion, scores, lls, params, n_samples, models)
