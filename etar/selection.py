"""Choosing the number of phases by BIC or AIC (thesis 4.2).

Two ways to put the criterion to the demonstrations:

- ``select_order`` (pooled): one fit per candidate over all demonstrations
  together, the candidate with the lowest score wins;
- ``vote_order`` (per demonstration, what the thesis did in 6.1: "BIC was used
  for estimating the model number ... for all the six separate
  demonstrations"): each demonstration chooses on its own, the number most of
  them choose wins (ties go to fewer phases).

They answer different questions.  The fit's gain from one more phase grows
with the number of samples N, the penalty only with log N, so pooled over
many demonstrations BIC keeps adding phases for any repeatable within-phase
detail (a hand lagging after each turn); one demonstration asks how many
phases a single execution of the task shows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Iterator, Sequence

from etar.demonstrations import check_demonstrations
from etar.model import ETAR
from etar.vocabulary import CRITERIA

METHODS = ("per_demonstration", "pooled")


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

    def to_dict(self) -> dict:
        """JSON-ready summary (no models)."""
        return dict(method="pooled", criterion=self.criterion, **self._scores_dict())

    def _scores_dict(self) -> dict:
        return dict(best=self.best, n_samples=self.n_samples, scores={str(k): v for k, v in self.scores.items()},
                    log_likelihoods={str(k): v for k, v in self.log_likelihoods.items()},
                    n_parameters={str(k): v for k, v in self.n_parameters.items()})

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


def fit_candidate(job: tuple) -> ETAR:
    """One candidate's fit: a module-level function of plain values, so that a
    process pool's ``map`` can run it (``fit_map``); ``job`` as ``vote_jobs`` makes them."""
    demos, k, transitions, model_options, max_iter, tol, seed = job
    return ETAR(k, transitions, **model_options).fit(demos, max_iter=max_iter, tol=tol, seed=seed)


def _fits(fit_map: Callable, jobs: list, labels: list, progress) -> Iterator[ETAR]:
    """The models of ``jobs`` run through ``fit_map``, in order; as each is taken,
    ``progress`` hears ``fit i/N done: <label>, ...`` (a pool's ``map`` runs ahead, so
    the line comes when that fit and every one before it are done)."""
    total = len(jobs)
    for i, (label, model) in enumerate(zip(labels, fit_map(fit_candidate, jobs)), 1):
        if progress:
            r = model.fit_report_
            progress(f"fit {i}/{total} done: {label}, log-likelihood {r.log_likelihood:.2f}, "
                     f"{r.n_iter} EM iterations ({r.seconds:.1f} s)")
        yield model


def _candidates(demos, candidates, transitions, progress) -> tuple[dict, int]:
    """(parameter count of each candidate that has fewer parameters than steps, in
    order; the number of steps); the others are reported through ``progress``."""
    n, m = demos[0][0].shape[1], demos[0][1].shape[1]
    d = n if transitions == "state" else m
    n_samples = sum(s.shape[0] - 1 for s, _ in demos)
    params = {}
    for k in candidates:
        p = ETAR.count_free_parameters(k, n, m, d)
        if p > n_samples:
            if progress:
                progress(f"K={k}: skipped, {p} parameters exceed {n_samples} steps")
            continue
        params[k] = p
    return params, n_samples


def _check_candidates(criterion, candidates) -> list[int]:
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    candidates = sorted({int(k) for k in candidates})
    if not candidates or candidates[0] < 1:
        raise ValueError(f"candidates must be positive integers, got {candidates!r}")
    return candidates


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
    fit_map: Callable = map,
    fit_progress: Callable[[str], None] | None = None,
    **model_options,
) -> OrderSelection:
    """Fit one model per candidate number of phases and score each.

    The parameter count is that of this model (``ETAR.count_free_parameters``),
    not of a plain Gaussian HMM.  Candidates with fewer steps than parameters
    are skipped (and reported through ``progress``); at least one must fit.
    ``fit_map``: how the candidates' fits are run, ``map`` or a ``map`` that runs
    them in parallel (``concurrent.futures.Executor.map``); each fit is seeded
    alone, so the result does not depend on it.  ``fit_progress`` hears
    ``fit i/N done: K=k, ...`` as each fit comes back.
    """
    candidates = _check_candidates(criterion, candidates)
    demos = check_demonstrations(demos)
    params, n_samples = _candidates(demos, candidates, transitions, progress)
    jobs = [(demos, k, transitions, model_options, max_iter, tol, seed) for k in params]
    fitted = _fits(fit_map, jobs, [f"K={k}" for k in params], fit_progress)
    return _scored(dict(zip(params, fitted)), params, n_samples, criterion, candidates, progress)


def _scored(fitted: dict, params: dict, n_samples: int, criterion: str, candidates, progress) -> OrderSelection:
    scores, lls, models = {}, {}, {}
    for k, model in fitted.items():
        p = params[k]
        ll = model.fit_report_.log_likelihood
        scores[k] = information_criterion(ll, p, n_samples, criterion)
        lls[k], models[k] = ll, model
        if progress:
            progress(f"K={k}: log-likelihood {ll:.2f}, {p} parameters, {criterion.upper()} {scores[k]:.2f} "
                     f"({model.fit_report_.seconds:.1f} s)")
    if not scores:
        raise ValueError(f"no candidate in {candidates} has fewer parameters than the {n_samples} steps")
    best = min(scores, key=scores.get)
    return OrderSelection(best, criterion, scores, lls, params, n_samples, models)


@dataclass(frozen=True)
class OrderVote:
    """Per-demonstration selection: ``best`` is the number of phases most
    demonstrations chose; ``votes``: candidate -> how many chose it;
    ``per_demonstration``: each demonstration's own ``OrderSelection``."""

    best: int
    criterion: str
    votes: dict
    per_demonstration: tuple

    def table(self) -> str:
        """Demonstrations as rows, candidates as columns, each row's choice marked."""
        ks = sorted({k for sel in self.per_demonstration for k in sel.scores})
        lines = [f"{'demo':>4} {'samples':>7} " + " ".join(f"{f'K={k}':>11}" for k in ks) + "  chosen"]
        for i, sel in enumerate(self.per_demonstration):
            cells = [f"{sel.scores[k]:>10.1f}{'*' if k == sel.best else ' '}" if k in sel.scores else f"{'-':>11}"
                     for k in ks]
            lines.append(f"{i:>4} {sel.n_samples:>7} " + " ".join(cells) + f"  {sel.best}")
        votes = ", ".join(f"{k}: {self.votes[k]}" for k in sorted(self.votes))
        lines.append(f"{self.criterion.upper()} per demonstration, votes {{{votes}}} -> {self.best} phases")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-ready summary (no models)."""
        return dict(method="per_demonstration", criterion=self.criterion, best=self.best,
                    votes={str(k): v for k, v in sorted(self.votes.items())},
                    per_demonstration=[sel._scores_dict() for sel in self.per_demonstration])


def vote_jobs(demo, candidates, transitions: str, model_options: dict, max_iter: int, tol: float,
              seed: int) -> list[tuple]:
    """The candidate fits ``vote_order`` runs for one (checked) demonstration, in its order,
    as jobs for ``fit_candidate``: a caller that has one demonstration before the others can
    start its fits then (``services.run.learn``) and hand their models over through
    ``fit_map``."""
    params, _ = _candidates([demo], candidates, transitions, None)
    return [([demo], k, transitions, model_options, max_iter, tol, seed) for k in params]


def demonstration_fits(pair, candidates: Sequence[int] = (1, 2, 3, 4, 5, 6), criterion: str = "bic", *,
                       transitions: str = "effect", seed: int = 0, max_iter: int = 200, tol: float = 1e-7,
                       **model_options) -> list[tuple]:
    """``vote_jobs`` for one (states, forces) pair with ``vote_order``'s checks and defaults:
    the fits ``vote_order`` of the same options runs for it."""
    (demo,) = check_demonstrations([pair])
    return vote_jobs(demo, _check_candidates(criterion, candidates), transitions, model_options, max_iter, tol, seed)


def vote_order(
    demos: Sequence,
    candidates: Sequence[int] = (1, 2, 3, 4, 5, 6),
    criterion: str = "bic",
    *,
    progress: Callable[[str], None] | None = None,
    transitions: str = "effect",
    seed: int = 0,
    max_iter: int = 200,
    tol: float = 1e-7,
    fit_map: Callable = map,
    fit_progress: Callable[[str], None] | None = None,
    **model_options,
) -> OrderVote:
    """Score the candidates on each demonstration alone (``select_order`` with
    the same options) and take the number of phases most of them choose.
    ``fit_map`` runs every (demonstration, candidate) fit, in one batch;
    ``progress`` hears each demonstration's choice, ``fit_progress``
    ``fit i/N done: K=k demonstration d, ...`` as each fit comes back.

    The chosen model is not fitted here: fit it on all demonstrations with
    ``ETAR(vote.best, ...)``.
    """
    candidates = _check_candidates(criterion, candidates)
    demos = check_demonstrations(demos)
    plans = [_candidates([demo], candidates, transitions, None) for demo in demos]
    jobs = [job for demo in demos for job in vote_jobs(demo, candidates, transitions, model_options, max_iter, tol,
                                                       seed)]
    labels = [f"K={k} demonstration {i}" for i, (params, _) in enumerate(plans) for k in params]
    # in order: each demonstration's candidates, one after the other
    models = _fits(fit_map, jobs, labels, fit_progress)
    selections = []
    for i, (params, n_samples) in enumerate(plans):
        sel = _scored({k: next(models) for k in params}, params, n_samples, criterion, candidates, None)
        if progress:
            progress(f"demonstration {i}: {criterion.upper()} chooses {sel.best} phases "
                     f"({sel.n_samples} steps; " + ", ".join(f"K={k} {v:.0f}" for k, v in sel.scores.items()) + ")")
        selections.append(sel)
    votes: dict = {}
    for sel in selections:
        votes[sel.best] = votes.get(sel.best, 0) + 1
    top = max(votes.values())
    best = min(k for k, v in votes.items() if v == top)  # a tie goes to the simpler model
    return OrderVote(best, criterion, votes, tuple(selections))


def fit_order(
    demos: Sequence,
    candidates: Sequence[int] = (1, 2, 3, 4, 5, 6),
    criterion: str = "bic",
    method: str = "per_demonstration",
    *,
    transitions: str = "effect",
    seed: int = 0,
    max_iter: int = 200,
    tol: float = 1e-7,
    progress: Callable[[str], None] | None = None,
    fit_map: Callable = map,
    **model_options,
) -> tuple[ETAR, dict]:
    """Choose the number of phases by ``method`` (``vote_order`` for
    per_demonstration, ``select_order`` for pooled) and return (the model with
    that many phases fitted to all demonstrations, the selection's JSON-ready
    summary).  The tables go to ``progress``, and ``fit i/N done`` as each candidate's
    fit comes back; ``fit_map`` runs the candidates' fits (``select_order``)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    say = progress or (lambda msg: None)
    options = dict(transitions=transitions, seed=seed, max_iter=max_iter, tol=tol, progress=progress, fit_map=fit_map,
                   fit_progress=progress, **model_options)
    if method == "pooled":
        sel = select_order(demos, candidates, criterion, **options)
        say(sel.table())
        return sel.model, sel.to_dict()
    vote = vote_order(demos, candidates, criterion, **options)
    say(vote.table())
    say(f"fitting {vote.best} phases to all {len(demos)} demonstrations")
    model = ETAR(vote.best, transitions, **model_options).fit(demos, max_iter=max_iter, tol=tol, seed=seed,
                                                              progress=progress)
    return model, vote.to_dict()
