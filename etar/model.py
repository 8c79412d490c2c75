"""The ETAR model: hyperparameters, parameters, and the calls that use them.

The model only holds parameters and builds the arrays that the pure functions in
``etar.inference`` and ``etar.em`` work on; its file is ``etar.model_file``.
Parameters are plain, assignable attributes, of these shapes:

- ``A``     (K, n, n)     state matrix of each phase
- ``B``     (K, n, m+1)   effect-of-action matrix (last column: intercept)
- ``Sigma`` (K, n, n)     noise covariance of each phase
- ``W``     (K+1, K, d+1) softmax weights: W[0] initial phase, W[i+1] out of phase i
- ``goal``  (n,) or None  STAR only: the end point the transition features are relative to

For ETAR (``transitions="effect"``) d = m and phi_t = [f_t; 1].  For STAR
(``transitions="state"``, thesis 6.3) d = n and phi_t = [s_t - goal; 1]; the
dynamics still take [f_t; 1], only the transition features change.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from threadpoolctl import threadpool_limits

from etar import em, inference
from etar.vocabulary import TRANSITIONS
from etar.demonstrations import DemonstrationError, check_demonstration, check_demonstrations, step_arrays
from etar.model_file import model_from_dict, model_to_dict, read_model_file, write_model_file

PROGRESS_EVERY = 50  # EM iterations between the progress lines of a long run


@dataclass(frozen=True)
class FitReport:
    """What one call to ``fit`` did."""

    log_likelihood: float
    objective: float
    n_iter: int
    converged: bool
    n_samples: int
    seconds: float
    seed: int
    history: tuple
    restart_objectives: tuple


def _finite(value) -> bool:
    """``math.isfinite``, False rather than OverflowError for an integer past float64's range
    (a model file's JSON may hold one)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def checked_parameters(A, B, Sigma, W, goal, n_phases: int, transitions: str):
    """Validated float64 copies of a model's parameters: (C = [A B], Sigma, W, goal),
    goal None but for STAR; a ``ValueError`` names the array that does not fit."""
    K = n_phases
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    Sigma = np.asarray(Sigma, dtype=np.float64)
    W = np.asarray(W, dtype=np.float64)
    if A.ndim != 3 or A.shape[0] != K or A.shape[1] != A.shape[2]:
        raise ValueError(f"A must have shape (K={K}, n, n), got {A.shape}")
    n = A.shape[1]
    if B.ndim != 3 or B.shape[:2] != (K, n) or B.shape[2] < 1:
        raise ValueError(f"B must have shape (K={K}, n={n}, m+1), got {B.shape}")
    if Sigma.shape != (K, n, n):
        raise ValueError(f"Sigma must have shape ({K}, {n}, {n}), got {Sigma.shape}")
    m = B.shape[2] - 1
    d = n if transitions == "state" else m
    if W.shape != (K + 1, K, d + 1):
        raise ValueError(f"W must have shape (K+1={K + 1}, K={K}, d+1={d + 1}), got {W.shape}")
    for name, arr in (("A", A), ("B", B), ("Sigma", Sigma), ("W", W)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains non-finite values")
    goal = None if transitions != "state" or goal is None else np.asarray(goal, dtype=np.float64)
    if goal is not None and goal.shape != (n,):
        raise ValueError(f"goal must have shape ({n},), got {goal.shape}")
    C = np.ascontiguousarray(np.concatenate([A, B], axis=2))
    return C, np.ascontiguousarray(Sigma), np.ascontiguousarray(W), goal


class ETAR:
    """Effect-of-action based transitions auto-regressive HMM (thesis section 4).

    Hyperparameters go to the constructor; ``fit`` sets the parameters.  A model
    whose parameters were assigned by hand works without ``fit``.
    """

    def __init__(
        self,
        n_phases: int,
        transitions: str = "effect",
        *,
        n_restarts: int = 4,
        init_iter: int = 15,
        solver: str = "gd",
        w_steps: int = 3,
        w_l2: float = 1e-3,
        sigma_prior_weight: float = 1.0,
        sigma_prior_scale: float | None = None,
        ab_prior: float = 1e-6,
        window: int = 10,
    ):
        if not isinstance(n_phases, (int, np.integer)) or n_phases < 1:
            raise ValueError(f"n_phases must be a positive integer, got {n_phases!r}")
        if transitions not in TRANSITIONS:
            raise ValueError(f"transitions must be one of {TRANSITIONS}, got {transitions!r}")
        if solver not in ("gd", "lbfgs"):
            raise ValueError(f"solver must be 'gd' or 'lbfgs', got {solver!r}")
        for name, value in (("w_l2", w_l2), ("sigma_prior_weight", sigma_prior_weight), ("ab_prior", ab_prior)):
            if not (value >= 0 and _finite(value)):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        if sigma_prior_scale is not None and not (sigma_prior_scale > 0 and _finite(sigma_prior_scale)):
            raise ValueError(f"sigma_prior_scale must be > 0 or None, got {sigma_prior_scale!r}")
        if n_restarts < 1:
            raise ValueError(f"n_restarts must be >= 1, got {n_restarts!r}")
        self.n_phases = int(n_phases)
        self.transitions = transitions
        self.n_restarts = int(n_restarts)
        self.init_iter = int(init_iter)
        self.solver = solver
        self.w_steps = int(w_steps)
        self.w_l2 = float(w_l2)
        self.sigma_prior_weight = float(sigma_prior_weight)
        self.sigma_prior_scale = sigma_prior_scale
        self.ab_prior = float(ab_prior)
        self.window = int(window)
        self.A = None
        self.B = None
        self.Sigma = None
        self.W = None
        self.goal = None
        self.metadata: dict = {}  # free-form, JSON-serialisable; saved with the model
        self.fit_report_: FitReport | None = None

    # ------------------------------------------------------------------
    # sizes and the parameter count
    # ------------------------------------------------------------------

    @property
    def n_state(self) -> int:
        self._require_parameters()
        return self.A.shape[1]

    @property
    def n_force(self) -> int:
        self._require_parameters()
        return self.B.shape[2] - 1

    @property
    def n_features(self) -> int:
        """d: the transition feature dimension without the constant."""
        return self.n_state if self.transitions == "state" else self.n_force

    @staticmethod
    def count_free_parameters(n_phases: int, n: int, m: int, d: int | None = None) -> int:
        """Free parameters of ETAR/STAR (used by BIC/AIC and the data-size check).

        Per phase: A n^2, B n(m+1), Sigma n(n+1)/2.  Softmax weights: each of the
        K+1 blocks has K(d+1) entries, but adding the same vector to every row
        leaves the probabilities unchanged, so (K-1)(d+1) of them are free.
        (A plain Gaussian HMM would count K-1 + K(K-1) + emissions; this model's
        transitions and initial distribution are regressions on the features.)
        """
        d = m if d is None else d
        K = n_phases
        per_phase = n * n + n * (m + 1) + n * (n + 1) // 2
        return K * per_phase + (K + 1) * (K - 1) * (d + 1)

    @property
    def n_free_parameters(self) -> int:
        return self.count_free_parameters(self.n_phases, self.n_state, self.n_force, self.n_features)

    # ------------------------------------------------------------------
    # parameter checks
    # ------------------------------------------------------------------

    def _require_parameters(self):
        if any(p is None for p in (self.A, self.B, self.Sigma, self.W)):
            raise RuntimeError("the model has no parameters yet: call fit() or assign A, B, Sigma and W")

    def _checked_parameters(self):
        """Validated float64 copies: (C = [A B], Sigma, W, goal)."""
        self._require_parameters()
        return checked_parameters(self.A, self.B, self.Sigma, self.W, self.goal, self.n_phases, self.transitions)

    def _set_parameters(self, C, Sigma, W):
        n = C.shape[1]
        self.A = np.ascontiguousarray(C[:, :, :n])
        self.B = np.ascontiguousarray(C[:, :, n:])
        self.Sigma = np.ascontiguousarray(Sigma)
        self.W = np.ascontiguousarray(W)

    def _steps(self, demos, goal):
        return [step_arrays(s, f, self.transitions, goal) for s, f in demos]

    # ------------------------------------------------------------------
    # learning
    # ------------------------------------------------------------------

    def fit(
        self,
        demos: Sequence,
        max_iter: int = 200,
        tol: float = 1e-7,
        seed: int = 0,
        progress: Callable[[str], None] | None = None,
        start_labels: Sequence | None = None,
    ) -> "ETAR":
        """Learn the parameters from demonstrations by EM.

        ``demos``: list of ``(states (T, n), forces (T, m))``, lengths may differ.
        ``tol``: mean objective gain per sample per iteration (nats) below which
        EM stops (see ``em.ConvergenceMonitor``).  ``n_restarts`` segment-based
        initialisations run ``init_iter`` iterations each; the best continues
        for up to ``max_iter`` iterations.  The same seed gives the same result.
        ``start_labels``: a phase (0..K-1) per step of every demonstration (T - 1
        labels, step t -> t+1's, as ``load_demonstration``'s ``phases``), e.g. the
        true phases of simulated ones, every phase present; EM starts once from the
        segmentation they give, for up to ``max_iter`` iterations, instead of the
        restarts.
        """
        # numba's parallel E-step takes both cores; OpenBLAS threads spinning
        # beside it for the small M-step products cost 3-4x (measured)
        with threadpool_limits(limits=1, user_api="blas"):
            return self._fit(demos, max_iter, tol, seed, progress, start_labels)

    def _fit(self, demos, max_iter, tol, seed, progress, start_labels=None):
        start = time.perf_counter()
        demos = check_demonstrations(demos)
        n, m = demos[0][0].shape[1], demos[0][1].shape[1]
        d = n if self.transitions == "state" else m
        n_samples = sum(s.shape[0] - 1 for s, _ in demos)
        n_params = self.count_free_parameters(self.n_phases, n, m, d)
        if n_samples < n_params:
            raise DemonstrationError(
                f"{n_samples} steps in {len(demos)} demonstration(s) are fewer than the "
                f"{n_params} free parameters of a {self.n_phases}-phase model with n={n}, m={m}; "
                "record more data or use fewer phases"
            )
        if max_iter < 0:
            raise ValueError(f"max_iter must be >= 0, got {max_iter}")
        rng = np.random.default_rng(seed)
        priors = _priors(demos, self.sigma_prior_weight, self.sigma_prior_scale, self.ab_prior, self.w_l2)
        stacked = em.StackedSteps.from_steps(self._steps(demos, None))
        K = self.n_phases

        def say(msg):
            if progress is not None:
                progress(msg)

        candidates = []
        given = None if start_labels is None else _step_labels(start_labels, demos, K)
        restarts = 1 if given is not None else self.n_restarts
        for r in range(restarts):
            labels = given if given is not None else em.segment_labels(stacked.starts, K, None if r == 0 else rng)
            W0 = np.zeros((K + 1, K, d + 1))
            C, Sigma, W = em.m_step(stacked, em.hard_expectations(labels, stacked.starts, K), W0,
                                    priors, self.solver, w_steps=30)
            mon = em.ConvergenceMonitor(tol, self.init_iter if restarts > 1 else max_iter,
                                        n_samples, self.window)
            params = _run_em(stacked, (C, Sigma, W), priors, mon, self.solver, self.w_steps, progress)
            candidates.append((mon.history[-1], params, mon))
            say(f"restart {r + 1}/{restarts}: objective {mon.history[-1]:.3f} "
                f"after {mon.n_iter} iterations")
        best = int(np.argmax([c[0] for c in candidates]))
        _, params, mon = candidates[best]
        if restarts > 1:
            # the continued run re-scores the same parameters first: drop that entry
            history = mon.history[:-1]
            mon = em.ConvergenceMonitor(tol, max_iter + len(history), n_samples, self.window, list(history))
            say(f"restart {best + 1} continues, up to {mon.max_iter} EM iterations in all")
            params = _run_em(stacked, params, priors, mon, self.solver, self.w_steps, progress)
        C, Sigma, W = params
        self._set_parameters(C, Sigma, W)
        if self.transitions == "state":
            self.goal = np.mean([s[-1] for s, _ in demos], axis=0)
        ll = em.e_step(stacked, C, Sigma, W).log_likelihood
        self.fit_report_ = FitReport(
            log_likelihood=float(ll),
            objective=float(mon.history[-1]),
            n_iter=mon.n_iter,
            converged=mon.converged,
            n_samples=n_samples,
            seconds=time.perf_counter() - start,
            seed=int(seed),
            history=tuple(mon.history),
            restart_objectives=tuple(float(c[0]) for c in candidates),
        )
        say(f"K={K}: log-likelihood {ll:.3f}, {mon.n_iter} iterations, "
            f"{'converged' if mon.converged else 'stopped at max_iter'}")
        return self

    # ------------------------------------------------------------------
    # inference
    # ------------------------------------------------------------------

    def _inference_arrays(self, states, forces, index=0):
        C, Sigma, W, goal = self._checked_parameters()
        n, m = C.shape[1], C.shape[2] - C.shape[1] - 1
        s, f = check_demonstration(states, forces, index=index, n=n, m=m)
        steps = step_arrays(s, f, self.transitions, None)
        chol_inv, log_norm = em.emission_arrays(Sigma)
        log_emis = inference.log_emissions(steps.regressors, steps.next_states, C, chol_inv, log_norm)
        log_initial, trans, log_trans = inference.initial_and_transitions(steps.features, W)
        return log_initial, trans, log_trans, log_emis

    def log_likelihood(self, demos: Sequence) -> float:
        """Total natural-log likelihood of a list of demonstrations."""
        demos = list(demos)
        if not demos:
            raise DemonstrationError("no demonstrations given")
        total = 0.0
        for i, demo in enumerate(demos):
            try:
                states, forces = demo
            except (TypeError, ValueError):
                raise DemonstrationError(f"demonstration {i}: expected a (states, forces) pair") from None
            li, tr, lt, le = self._inference_arrays(states, forces, i)
            total += inference.forward(li, tr, lt, le)[1].sum()
        return float(total)

    def posterior(self, states, forces) -> np.ndarray:
        """(T-1, K) smoothed phase probabilities p(rho_t | whole demonstration)."""
        ll, gamma, _ = inference.smoother(*self._inference_arrays(states, forces))
        if not math.isfinite(ll):
            raise ValueError("the demonstration is impossible under every phase path of this model")
        return gamma

    def viterbi(self, states, forces) -> np.ndarray:
        """(T-1,) most likely phase index of every step."""
        li, _, lt, le = self._inference_arrays(states, forces)
        path, best = inference.viterbi(li, lt, le)
        if not math.isfinite(best):
            raise ValueError("the demonstration is impossible under every phase path of this model")
        return path

    def filter(self, goal=None, start: str = "first") -> "PhaseFilter":
        """An online forward filter (what the phase estimator runs).

        For STAR, ``goal`` overrides the model's stored end point.  ``start``: "first"
        (a task from its beginning: the learned initial-phase prior) or "uniform" (a
        filter joining a task under way, e.g. a restarted estimator: every phase
        equally likely until the samples say which).
        """
        return PhaseFilter(self, goal, start)

    # ------------------------------------------------------------------
    # file format
    # ------------------------------------------------------------------

    def to_dict(self) -> dict:
        return model_to_dict(self)

    def save(self, path) -> None:
        """Write the model as JSON (format in docs/model-format.md)."""
        write_model_file(path, self.to_dict())

    @classmethod
    def from_dict(cls, data: dict, source: str = "<dict>") -> "ETAR":
        return model_from_dict(cls, data, source)

    @classmethod
    def load(cls, path) -> "ETAR":
        path = Path(path)
        return cls.from_dict(read_model_file(path), str(path))


def _priors(demos, sigma_prior_weight: float, sigma_prior_scale: float | None, ab_prior: float,
            w_l2: float) -> em.Priors:
    """The weak priors of a fit to ``demos``; without a ``sigma_prior_scale`` the
    covariance prior's scale follows the demonstrations' motion."""
    n = demos[0][0].shape[1]
    if sigma_prior_scale is not None:
        scale = sigma_prior_scale * np.eye(n)
    else:
        # a thousandth of the mean square one-step motion, per state dimension
        msq = np.mean(np.vstack([np.diff(s, axis=0) ** 2 for s, _ in demos]), axis=0)
        msq = np.where(msq > 0, msq, 1e-12)
        scale = np.diag(1e-3 * msq)
    return em.Priors(sigma_prior_weight, scale, ab_prior, w_l2)


def _run_em(stacked, params, priors, monitor: em.ConvergenceMonitor, solver: str, w_steps: int,
            progress=None):
    """Alternate E- and M-steps until the monitor is done; returns the last
    parameters, which are also the ones the last reported objective scored.
    ``progress`` hears every ``PROGRESS_EVERY``-th iteration of a longer run."""
    C, Sigma, W = params
    while True:
        ex = em.e_step(stacked, C, Sigma, W)
        if not math.isfinite(ex.log_likelihood):
            raise FloatingPointError(
                f"log-likelihood became {ex.log_likelihood} at iteration {monitor.n_iter}; "
                "check for duplicated or constant data"
            )
        monitor.report(ex.log_likelihood + em.log_prior(C, Sigma, W, priors, stacked.center))
        if monitor.done:
            return C, Sigma, W
        if progress is not None and monitor.n_iter and monitor.n_iter % PROGRESS_EVERY == 0:
            progress(f"  EM iteration {monitor.n_iter}/{monitor.max_iter}: objective {monitor.history[-1]:.3f}")
        C, Sigma, W = em.m_step(stacked, ex, W, priors, solver, w_steps)


def _step_labels(start_labels, demos, K: int) -> np.ndarray:
    """Stacked step labels, checked against the demonstrations and the phases."""
    if len(start_labels) != len(demos):
        raise ValueError(f"start_labels: {len(start_labels)} label sequences for {len(demos)} demonstrations")
    out = []
    for i, (labels, (s, _)) in enumerate(zip(start_labels, demos)):
        labels = np.asarray(labels)
        if labels.shape != (s.shape[0] - 1,) or not np.issubdtype(labels.dtype, np.integer):
            raise ValueError(f"start_labels[{i}]: expected {s.shape[0] - 1} integer phases (one per step), "
                             f"got {labels.dtype} {labels.shape}")
        if labels.size and (labels.min() < 0 or labels.max() >= K):
            raise ValueError(f"start_labels[{i}]: phases must be 0..{K - 1}, got {labels.min()}..{labels.max()}")
        out.append(labels.astype(np.int64))
    stacked = np.concatenate(out)
    missing = sorted(set(range(K)) - set(np.unique(stacked).tolist()))
    if missing:
        raise ValueError(f"start_labels: phase(s) {missing} label no step; a phase needs steps to start from")
    return stacked


class PhaseFilter:
    """Online forward filter: ``update(state, force)`` after every new sample.

    Returns the normalised forward message p(rho_{t-1} | samples 0..t) as (K,)
    probabilities.  The very first sample returns the prior of the first phase.
    A non-finite sample raises ``ValueError`` and leaves the filter unchanged.
    The compiled step is the same kernel as the batch forward pass.  With
    ``start="uniform"`` the first sample gives every phase the same probability
    instead of the learned initial-phase prior (a filter that joins a task under way).
    """

    def __init__(self, model: ETAR, goal=None, start: str = "first"):
        if start not in ("first", "uniform"):
            raise ValueError(f"start must be 'first' or 'uniform', got {start!r}")
        self.start = start
        C, Sigma, W, stored_goal = model._checked_parameters()
        self._C, self._W = C, W
        self._chol_inv, self._log_norm = em.emission_arrays(Sigma)
        K, n, p = C.shape
        m = p - n - 1
        self.n_phases, self.n_state, self.n_force = K, n, m
        self._use_state = model.transitions == "state"
        g = goal if goal is not None else stored_goal
        if self._use_state and g is None:
            raise ValueError("a STAR filter needs a goal: pass goal= or fit the model")
        self._goal = np.zeros(n) if g is None else np.array(g, dtype=np.float64).reshape(n)
        self._prev_state = np.zeros(n)
        self._prev_force = np.zeros(m)
        self._flags = np.zeros(2, dtype=np.bool_)
        self._alpha = np.zeros(K)
        self._log_alpha = np.zeros(K)
        self._x = np.zeros(p)
        self._phi = np.zeros((n if self._use_state else m) + 1)
        self._r = np.zeros(n)
        self._log_emis = np.zeros(K)
        self._trans = np.zeros((K, K))
        self._log_trans = np.zeros((K, K))
        self._new_alpha = np.zeros(K)
        self._new_log_alpha = np.zeros(K)
        self.n_updates = 0

    def reset(self) -> None:
        self._flags[:] = False
        self.n_updates = 0

    def _sample(self, state, force, caller: str) -> tuple[np.ndarray, np.ndarray]:
        s = np.asarray(state, dtype=np.float64)
        f = np.asarray(force, dtype=np.float64)
        if s.shape != (self.n_state,) or f.shape != (self.n_force,):
            raise ValueError(
                f"{caller} expects state ({self.n_state},) and force ({self.n_force},), got {s.shape} and {f.shape}"
            )
        return s, f

    @staticmethod
    def _non_finite(s: np.ndarray, f: np.ndarray) -> ValueError:
        return ValueError(f"non-finite sample: state={s.tolist()} force={f.tolist()}; filter unchanged")

    def update(self, state, force) -> np.ndarray:
        s, f = self._sample(state, force, "update")
        status = inference.filter_update(
            s, f, self._goal, self._use_state, self._prev_state, self._prev_force, self._flags,
            self._alpha, self._log_alpha, self._C, self._chol_inv, self._log_norm, self._W,
            self._x, self._phi, self._r, self._log_emis, self._trans, self._log_trans,
            self._new_alpha, self._new_log_alpha,
        )
        if status == 1:
            raise self._non_finite(s, f)
        if status == 2:
            raise ValueError("sample impossible under every phase (check units); filter unchanged")
        if self.n_updates == 0 and self.start == "uniform":
            # the first sample only forms the prior of its phase: joining a task under
            # way, the learned prior (of the task's first phase) would be wrong
            self._alpha[:] = 1.0 / self.n_phases
            self._log_alpha[:] = -math.log(self.n_phases)
        self.n_updates += 1
        return self._alpha.copy()

    def anchor(self, state, force) -> np.ndarray:
        """Take a sample without conditioning on the step that ends at it.

        For a step the phase's law did not drive (the KRC held the arm in monitor
        mode) or one whose start is missing (a skipped sample): the posterior
        stays what it was, and the sample becomes the start of the next step, so
        the estimate after a hold continues from the phase before it.  Before any
        sample it is ``update`` (the first sample conditions on no step either).
        """
        if not self._flags[0]:
            return self.update(state, force)
        s, f = self._sample(state, force, "anchor")
        if not (np.isfinite(s).all() and np.isfinite(f).all()):
            raise self._non_finite(s, f)
        self._prev_state[:] = s
        self._prev_force[:] = f
        return self._alpha.copy()
