"""Expectation-maximisation for ETAR as pure functions over arrays.

E-step: forward-backward per demonstration (``etar.inference``; thesis 4.3.1,
4.5).  M-step (thesis 4.3.2, 4.5), all demonstrations pooled:

- [A_j B_j]: weighted least squares (eq. 58/72), with a weak matrix-normal
  prior (precision ``ab_strength``) centred on A = I, B = 0 so that a phase
  with no data keeps a well-posed regression.  The regression is solved in
  "difference" coordinates (target s_{t+1} - s_t, states centred on their
  mean), which is the same model but far better conditioned.
- Sigma_j: weighted residual covariance (eq. 63/76) under a weak
  inverse-Wishart prior (``sigma_weight`` pseudo-samples of covariance
  ``sigma_scale``), so that a phase with little data cannot collapse.
- W: weighted softmax regression (eq. 67; its objective in
  ``etar.softmax_regression``) by gradient descent with Armijo backtracking
  (eq. 68, 73-74).  The gradient is preconditioned by Boehning's bound on the
  softmax Hessian, so one step length suits every feature scale (newtons next
  to a constant 1) and the first trial step always satisfies Armijo.
  ``solver="lbfgs"`` uses scipy's L-BFGS-B instead.

Every M-step is exact or a descent step on the penalised objective, so the
objective (log-likelihood + log-prior) never decreases.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numba
import numpy as np

from etar import inference
from etar.demonstrations import StepArrays
from etar.interrupts import interrupt_behind
from etar.softmax_regression import (bohning_factors, preconditioned_steps, softmax_regression_at,
                                     softmax_regression_objective)
from kernel_plumbing import blas

LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class Priors:
    """Weak priors that keep every phase finite (see the module docstring)."""

    sigma_weight: float  # nu0: pseudo-samples of the covariance prior
    sigma_scale: np.ndarray  # Psi (n, n)
    ab_strength: float  # lambda: precision of the prior on [A - I, B]
    w_l2: float  # L2 penalty on W


@dataclass
class ConvergenceMonitor:
    """EM stopping rule measured per sample, with the objective's history.

    Converged when the objective gained less than ``tol`` nats per sample per
    iteration, averaged over the last ``window`` iterations: EM on this model has
    long plateaus, so one small step is not taken for convergence.  Warns when
    the objective falls (it must not).
    """

    tol: float
    max_iter: int
    n_samples: int
    window: int = 10
    history: list = field(default_factory=list)

    def report(self, objective: float) -> None:
        if self.history:
            drop = self.history[-1] - objective
            if drop > 1e-9 * max(1.0, abs(objective)):
                warnings.warn(
                    f"EM objective decreased by {drop:.3g} nats at iteration {len(self.history)}",
                    RuntimeWarning,
                    stacklevel=3,
                )
        self.history.append(float(objective))

    @property
    def n_iter(self) -> int:
        """M-steps done so far (the first report scores the initial parameters)."""
        return max(len(self.history) - 1, 0)

    @property
    def converged(self) -> bool:
        if len(self.history) <= self.window:
            return False
        gain = self.history[-1] - self.history[-1 - self.window]
        return gain / (self.window * self.n_samples) < self.tol

    @property
    def done(self) -> bool:
        return self.converged or self.n_iter >= self.max_iter


# --------------------------------------------------------------------------
# demonstrations stacked once per fit
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class StackedSteps:
    """All demonstrations' steps stacked along the first axis (see inference)."""

    regressors: np.ndarray  # (N, p)
    next_states: np.ndarray  # (N, n)
    features: np.ndarray  # (N, d+1)
    starts: np.ndarray  # (D+1,) first step of each demonstration, then N
    center: np.ndarray  # (n,) mean state, for the difference coordinates
    xx: np.ndarray  # (N, p*p) outer products of centred regressors
    yx: np.ndarray  # (N, n*p) state differences times centred regressors
    yy: np.ndarray  # (N, n*n) outer products of state differences

    @classmethod
    def from_steps(cls, all_steps: list[StepArrays]) -> "StackedSteps":
        X = np.ascontiguousarray(np.vstack([s.regressors for s in all_steps]))
        Y = np.ascontiguousarray(np.vstack([s.next_states for s in all_steps]))
        F = np.ascontiguousarray(np.vstack([s.features for s in all_steps]))
        lengths = [s.regressors.shape[0] for s in all_steps]
        starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        n = Y.shape[1]
        center = X[:, :n].mean(axis=0)
        Xc = X.copy()
        Xc[:, :n] -= center
        dY = Y - X[:, :n]
        N, p = X.shape
        return cls(
            regressors=X, next_states=Y, features=F, starts=starts, center=center,
            xx=(Xc[:, :, None] * Xc[:, None, :]).reshape(N, p * p),
            yx=(dY[:, :, None] * Xc[:, None, :]).reshape(N, n * p),
            yy=(dY[:, :, None] * dY[:, None, :]).reshape(N, n * n),
        )

    @property
    def n_samples(self) -> int:
        return self.regressors.shape[0]


def to_difference_coordinates(C: np.ndarray, center: np.ndarray) -> np.ndarray:
    """[A B] -> [A - I, B_f, b + (A - I) mu]: the map from centred regressors to s_{t+1} - s_t."""
    K, n, p = C.shape
    D = C.copy()
    D[:, :, :n] -= np.eye(n)
    D[:, :, p - 1] += D[:, :, :n] @ center
    return D


def from_difference_coordinates(D: np.ndarray, center: np.ndarray) -> np.ndarray:
    K, n, p = D.shape
    C = D.copy()
    C[:, :, p - 1] -= D[:, :, :n] @ center
    C[:, :, :n] += np.eye(n)
    return C


# --------------------------------------------------------------------------
# E-step
# --------------------------------------------------------------------------


def emission_arrays(Sigma: np.ndarray):
    """Cholesky inverses and log normalisers of every phase's covariance."""
    K, n, _ = Sigma.shape
    # numpy's linalg runs the same LAPACK call on each matrix of a stack as on one alone
    # (the same bits), without the per-call overhead EM pays every iteration
    try:
        L = np.linalg.cholesky(Sigma)
    except np.linalg.LinAlgError:
        for j in range(K):
            try:
                np.linalg.cholesky(Sigma[j])
            except np.linalg.LinAlgError:
                raise ValueError(f"Sigma[{j}] is not symmetric positive definite: {Sigma[j].tolist()}") from None
        raise
    chol_inv = np.linalg.inv(L)
    log_norm = np.empty(K)
    for j in range(K):
        log_norm[j] = -0.5 * n * LOG_2PI - np.log(np.diag(L[j])).sum()
    return np.ascontiguousarray(chol_inv), log_norm


@dataclass
class Expectations:
    log_likelihoods: np.ndarray  # (D,) per demonstration
    gamma: np.ndarray  # (N, K)
    xi: np.ndarray  # (N, K, K); the first row of every demonstration is 0
    trans: np.ndarray | None = None  # (N, K, K) transitions under the W that produced them
    log_trans: np.ndarray | None = None

    @property
    def log_likelihood(self) -> float:
        return float(self.log_likelihoods.sum())


def e_step(stacked: StackedSteps, C, Sigma, W) -> Expectations:
    chol_inv, log_norm = emission_arrays(Sigma)
    ll, gamma, xi, trans, log_trans = inference.e_step_stacked(
        stacked.regressors, stacked.next_states, stacked.features, stacked.starts,
        np.ascontiguousarray(C), chol_inv, log_norm, np.ascontiguousarray(W),
    )
    return Expectations(ll, gamma, xi, trans, log_trans)


def log_prior(C, Sigma, W, priors: Priors, center) -> float:
    """Log density (up to a constant) of the weak priors at the parameters."""
    K, n, p = C.shape
    D = to_difference_coordinates(C, center)
    lam = priors.ab_strength
    dof = priors.sigma_weight + (p if lam > 0 else 0)
    scatter = np.empty_like(Sigma)
    for j in range(K):
        scatter[j] = priors.sigma_weight * priors.sigma_scale + lam * D[j] @ D[j].T
    # stacked: the same LAPACK calls per matrix (emission_arrays), fewer numpy calls
    _, logdets = np.linalg.slogdet(Sigma)
    solved = np.linalg.solve(Sigma, scatter)
    value = 0.0
    for j in range(K):
        value += -0.5 * dof * logdets[j] - 0.5 * np.trace(solved[j])
    value -= 0.5 * priors.w_l2 * float(np.sum(W * W))
    return float(value)


# --------------------------------------------------------------------------
# M-step
# --------------------------------------------------------------------------


def m_step_dynamics(stacked: StackedSteps, gamma: np.ndarray, priors: Priors):
    """[A_j B_j] and Sigma_j of every phase from the phase weights gamma (N, K)."""
    N, p = stacked.regressors.shape
    n = stacked.next_states.shape[1]
    K = gamma.shape[1]
    lam = priors.ab_strength
    Sxx = (gamma.T @ stacked.xx).reshape(K, p, p)
    Syx = (gamma.T @ stacked.yx).reshape(K, n, p)
    Syy = (gamma.T @ stacked.yy).reshape(K, n, n)
    Nk = gamma.sum(axis=0)
    D = np.empty((K, n, p))
    Sigma = np.empty((K, n, n))
    for j in range(K):
        # (Sxx + lam I) D^T = Syx^T; lstsq tolerates regressors that do not span
        # every direction when lam == 0
        D[j] = np.linalg.lstsq(Sxx[j] + lam * np.eye(p), Syx[j].T, rcond=None)[0].T
        cross = D[j] @ Syx[j].T
        residual = Syy[j] - cross - cross.T + D[j] @ Sxx[j] @ D[j].T
        scatter = residual + lam * D[j] @ D[j].T + priors.sigma_weight * priors.sigma_scale
        dof = Nk[j] + priors.sigma_weight + (p if lam > 0 else 0)
        S = scatter / dof
        Sigma[j] = 0.5 * (S + S.T)
    return from_difference_coordinates(D, stacked.center), Sigma


def _bohning_factors(features, targets, l2):
    """Cholesky factors of kron(1/2 (I - 11'/(K+1)), sum_t q_t phi_t phi_t') + l2 I
    per block: an upper bound on each block's Hessian (Boehning 1992); compiled where that
    gives these bits (numpy sums fewer than 8 numbers in order, as the kernel sums the trace)."""
    if features.shape[1] < 8 and _compiled("factors"):
        factors, info = bohning_factors(np.ascontiguousarray(features), targets.sum(axis=2), float(l2),
                                        targets.shape[2], blas.GEMM, blas.POTRF)
        if info == 0:
            return factors
        # not positive definite: numpy's own path below raises numpy's error
    return _bohning_factors_numpy(features, targets, l2)


def _bohning_factors_numpy(features, targets, l2):
    """``_bohning_factors`` in numpy (the reference the kernel is checked against)."""
    N, R, K = targets.shape
    q = targets.sum(axis=2)  # (N, R)
    A = 0.5 * (np.eye(K) - np.ones((K, K)) / (K + 1))
    d1 = features.shape[1]
    n = K * d1
    eye = np.eye(n)
    bounds = np.empty((R, n, n))
    for r in range(R):
        S = features.T @ (features * q[:, r : r + 1])
        ridge = max(l2, 1e-12 * (np.trace(S) + 1.0))
        # kron(A, S) as a broadcast product: the same products, without np.kron's
        # general-purpose reshaping (a third of this function's time)
        bounds[r] = (A[:, None, :, None] * S[None, :, None, :]).reshape(n, n) + ridge * eye
    # one call for the stack: LAPACK's potrf on each block, as block by block, without
    # numpy's per-call overhead (learning fits these thousands of times)
    return np.linalg.cholesky(bounds)


def fit_softmax_blocks(w, features, targets, l2, solver="gd", max_steps=1, at_w=None):
    """Improve weight blocks w (R, K, d+1) of the softmax transition model.

    ``targets`` (N, R, K) are the expected transition counts of each step.
    Minimises the weighted cross-entropy (``etar.softmax_regression``)
    starting from ``w``; never returns a worse block than it was given.
    ``at_w``: (values, grads) at ``w`` if the caller already has them.
    """
    R, K, d1 = w.shape
    if K == 1 or features.shape[0] == 0:
        return w.copy()
    if solver == "lbfgs":
        from scipy import optimize  # learning only: the services import this module and never fit

        out = w.copy()
        for r in range(R):
            tr = np.ascontiguousarray(targets[:, r : r + 1, :])

            def fun(flat, tr=tr):
                v, g = softmax_regression_objective(flat.reshape(1, K, d1), features, tr, l2)
                return v[0], g.ravel()

            v0 = fun(w[r].ravel())[0]
            res = optimize.minimize(fun, w[r].ravel(), jac=True, method="L-BFGS-B",
                                    options=dict(maxiter=max_steps))
            if res.fun <= v0:
                out[r] = res.x.reshape(K, d1)
        return out
    if solver != "gd":
        raise ValueError(f"solver must be 'gd' or 'lbfgs', got {solver!r}")
    factors = _bohning_factors(features, targets, l2)
    w = w.copy()
    if at_w is None:
        value, grad = softmax_regression_objective(w, features, targets, l2)
    else:
        value, grad = (a.copy() for a in at_w)
    # compiled where it runs on one thread anyway (a pool's fits, a sweep's): its objective
    # cannot be parallel inside the kernel, and on more threads numpy's path with the
    # parallel objective is the faster (6 demonstrations x 3000 samples: 9.3 against 10.2 ms an iteration)
    if numba.get_num_threads() == 1 and _compiled("steps"):
        out, v, g = w.copy(), value.copy(), grad.copy()
        # contiguous, as the check's: one compiled specialisation
        if preconditioned_steps(out, np.ascontiguousarray(features), np.ascontiguousarray(targets), float(l2),
                                factors, v, g, int(max_steps), blas.GESV, blas.DOT) == 0:
            return out
        # a solve failed: numpy's own path below raises numpy's error
    return _preconditioned_steps_numpy(w, features, targets, l2, factors, value, grad, max_steps)


def _preconditioned_steps_numpy(w, features, targets, l2, factors, value, grad, max_steps):
    """``preconditioned_steps`` in numpy (the reference it is checked against)."""
    R, K, d1 = w.shape
    active = np.ones(R, dtype=bool)
    for _ in range(max_steps):
        direction = np.zeros_like(w)
        slope = np.zeros(R)
        # L L^T direction = grad for every active block: LAPACK's gesv on each, in two calls
        # for the stack instead of two per block (the same solves, the same bits)
        todo = np.flatnonzero(active)
        L = factors[todo]
        y = np.linalg.solve(L, grad[todo].reshape(todo.size, K * d1, 1))
        direction[todo] = np.linalg.solve(np.swapaxes(L, 1, 2), y).reshape(todo.size, K, d1)
        for r in todo:
            g = grad[r].ravel()
            slope[r] = g @ direction[r].ravel()
            if slope[r] <= 1e-14 * max(1.0, abs(value[r])):
                active[r] = False
        if not active.any():
            break
        step = np.where(active, 1.0, 0.0)
        accepted = ~active
        cand_w = w.copy()
        for _ in range(40):  # Armijo backtracking, per block
            todo = ~accepted
            cand_w[todo] = w[todo] - step[todo, None, None] * direction[todo]
            cv, cg = softmax_regression_objective(cand_w, features, targets, l2)
            ok = cv <= value - 1e-4 * step * slope
            newly = todo & ok
            accepted |= newly
            if accepted.all():
                break
            step[~accepted] *= 0.5
        gain = np.where(accepted & active, value - cv, 0.0)
        keep = accepted & active
        w[keep] = cand_w[keep]
        value[keep] = cv[keep]
        grad[keep] = cg[keep]
        active &= keep & (gain > 1e-11 * np.maximum(1.0, np.abs(value)))
        if not active.any():
            break
    return w


# kernel -> whether it gives the numpy path's bits here ("steps": the descent, "factors"
# Boehning's bound's Cholesky factors), checked once a process
_CHECKED: dict = {}
_CHECK_SHAPES = ((1, 2, 1), (3, 2, 40), (4, 3, 300), (7, 6, 200))  # (blocks R, phases K, steps N)


def _compiled(kernel: str) -> bool:
    """Whether the compiled ``kernel`` may stand in for its numpy path: numpy's BLAS and LAPACK
    were found and, on random problems of EM's shapes, it gives the numpy path's bits."""
    if kernel not in _CHECKED:
        _CHECKED[kernel] = _same_bits(kernel)
    return _CHECKED[kernel]


def _same_bits(kernel: str) -> bool:
    if not blas.AVAILABLE or kernel == "factors" and not blas.POTRF:
        return False
    rng = np.random.default_rng(31)
    try:
        for R, K, N in _CHECK_SHAPES:
            features = np.hstack([rng.standard_normal((N, 3)) * 10.0, np.ones((N, 1))])
            targets = rng.dirichlet(np.ones(K), size=(N, R)) * rng.uniform(0.0, 1.0, (N, R, 1))
            if kernel == "factors":
                for l2 in (1e-3, 0.0):  # without l2, the ridge is the floor made of the trace
                    got, info = bohning_factors(features, targets.sum(axis=2), l2, K, blas.GEMM, blas.POTRF)
                    if info != 0 or not np.array_equal(got, _bohning_factors_numpy(features, targets, l2)):
                        return False
                continue
            factors = _bohning_factors_numpy(features, targets, 1e-3)
            w = rng.standard_normal((R, K, 4)) * 0.1
            value, grad = softmax_regression_objective(w, features, targets, 1e-3)
            expected = _preconditioned_steps_numpy(w.copy(), features, targets, 1e-3, factors, value.copy(),
                                                   grad.copy(), 3)
            got = w.copy()
            if preconditioned_steps(got, features, targets, 1e-3, factors, value.copy(), grad.copy(), 3,
                                    blas.GESV, blas.DOT) != 0 or not np.array_equal(got, expected):
                return False
    except Exception as exc:  # noqa: BLE001 - a kernel that will not compile: the numpy path
        interrupt = interrupt_behind(exc)
        if interrupt is not None:  # a Ctrl-C while it compiled or ran: not a verdict, and not to be lost
            raise interrupt from None
        return False
    return True


def m_step(stacked: StackedSteps, ex: Expectations, W, priors: Priors, solver="gd", w_steps=1):
    """New (C, Sigma, W) from the expectations of every demonstration."""
    C, Sigma = m_step_dynamics(stacked, ex.gamma, priors)
    K = ex.gamma.shape[1]
    W_new = W.copy()
    if K > 1:
        first = stacked.starts[:-1]
        W_new[:1] = fit_softmax_blocks(
            W[:1], np.ascontiguousarray(stacked.features[first]),
            np.ascontiguousarray(ex.gamma[first][:, None, :]), priors.w_l2, solver, w_steps,
        )
        at_w = None
        if ex.trans is not None:
            at_w = softmax_regression_at(W[1:], stacked.features, ex.xi, ex.trans, ex.log_trans, priors.w_l2)
        W_new[1:] = fit_softmax_blocks(W[1:], stacked.features, ex.xi, priors.w_l2, solver, w_steps, at_w)
    return C, Sigma, W_new


# --------------------------------------------------------------------------
# initialisation from segments
# --------------------------------------------------------------------------


def hard_expectations(labels: np.ndarray, starts: np.ndarray, K: int) -> Expectations:
    """One-hot gamma and xi from stacked phase labels (N,)."""
    N = labels.shape[0]
    gamma = np.zeros((N, K))
    gamma[np.arange(N), labels] = 1.0
    xi = np.zeros((N, K, K))
    later = np.ones(N, dtype=bool)
    later[starts[:-1]] = False
    t = np.flatnonzero(later)
    xi[t, labels[t - 1], labels[t]] = 1.0
    return Expectations(np.zeros(len(starts) - 1), gamma, xi)


def segment_labels(starts: np.ndarray, K: int, rng: np.random.Generator | None) -> np.ndarray:
    """Contiguous left-to-right segments in every demonstration, stacked (N,).

    ``rng=None`` gives equal-length segments; otherwise random cut points with
    every segment at least a fifth of the equal length.
    """
    out = []
    for a, b in zip(starts[:-1], starts[1:]):
        N = int(b - a)
        if K == 1 or N < K:
            out.append(np.minimum(np.arange(N) * K // max(N, 1), K - 1).astype(np.int64))
            continue
        if rng is None:
            cuts = [round(N * k / K) for k in range(1, K)]
        else:
            min_len = max(1, N // (5 * K))
            raw = np.sort(rng.uniform(0, N - K * min_len, size=K - 1))
            cuts = [int(raw[k]) + (k + 1) * min_len for k in range(K - 1)]
        labels = np.zeros(N, dtype=np.int64)
        for c in cuts:
            labels[c:] += 1
        out.append(labels)
    return np.concatenate(out)
