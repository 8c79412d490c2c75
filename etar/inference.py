"""Inference for the ETAR auto-regressive HMM as pure functions over arrays.

Nothing here sees a model object: callers build the arrays (``etar.em``,
``etar.model``) and these functions do the numerics, compiled with numba.
Float64 throughout; likelihoods, transitions and normalisers are carried as
logarithms and a forbidden transition is ``-inf``, never NaN.

Array conventions (0-based; one demonstration of T samples has T-1 phases,
phase ``t`` governs the step from sample ``t`` to ``t+1``):

- ``regressors``   (T-1, p = n+m+1)  x_t = [s_t; f_t; 1]
- ``next_states``  (T-1, n)          y_t = s_{t+1}
- ``features``     (T-1, d+1)        phi_t, the transition features of step t
- ``C``            (K, n, p)         [A_j B_j]
- ``chol_inv``     (K, n, n)         L_j^{-1} with Sigma_j = L_j L_j^T
- ``log_norm``     (K,)              -1/2 log|2 pi Sigma_j|
- ``W``            (K+1, K, d+1)     W[0] initial logits, W[i+1] logits out of phase i
- ``log_emis``     (T-1, K)          log N(y_t; C_j x_t, Sigma_j)
- ``log_initial``  (K,)              log p(rho_0 | phi_0)
- ``trans``, ``log_trans`` (T-1, K, K)  p(rho_t = j | rho_{t-1} = i, phi_t) and its log;
  row 0 is unused (nothing precedes the first phase) so that every array is
  indexed by the step t.

Several demonstrations are stacked along the first axis; ``starts`` (D+1,)
holds the first step of each and the total.  The forward pass keeps messages
normalised and adds the log normalisers; it predicts with probabilities and
falls back to an exact log-sum-exp where that product underflows, so it equals
a pure log-space pass (the brute-force tests check it) at a third of the cost.

The same step kernels (``emission_step``, ``transition_step``,
``condition_step``) serve the batch passes and the online filter, so the filter
that runs in the phase estimator is the one the tests check.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from kernel_plumbing.addresses import JIT as _JIT

_STEP = dict(_JIT, inline="always")


# --------------------------------------------------------------------------
# step kernels (shared by batch passes and the online filter)
# --------------------------------------------------------------------------


@njit(**_STEP)
def logsumexp(v):
    """log(sum(exp(v))) of a 1-D array; -inf when every entry is -inf."""
    m = -np.inf
    for i in range(v.shape[0]):
        if v[i] > m:
            m = v[i]
    if m == -np.inf:
        return -np.inf
    s = 0.0
    for i in range(v.shape[0]):
        s += math.exp(v[i] - m)
    return m + math.log(s)


@njit(**_STEP)
def emission_step(y, x, C, chol_inv, log_norm, r, out):
    """out[j] = log N(y; C[j] x, Sigma_j) for every phase j (r: scratch (n,))."""
    K, n, p = C.shape
    for j in range(K):
        for a in range(n):
            acc = y[a]
            for b in range(p):
                acc -= C[j, a, b] * x[b]
            r[a] = acc
        q = 0.0
        for a in range(n):
            z = 0.0
            for b in range(a + 1):  # chol_inv is lower triangular
                z += chol_inv[j, a, b] * r[b]
            q += z * z
        out[j] = log_norm[j] - 0.5 * q


@njit(**_STEP)
def softmax_step(w, phi, prob, logp):
    """prob = softmax(w @ phi) and logp = its log, for one block w (K, d+1)."""
    K, d1 = w.shape
    mx = -np.inf
    for j in range(K):
        acc = 0.0
        for f in range(d1):
            acc += w[j, f] * phi[f]
        logp[j] = acc
        if acc > mx:
            mx = acc
    s = 0.0
    for j in range(K):
        e = math.exp(logp[j] - mx)
        prob[j] = e
        s += e
    lse = mx + math.log(s)
    for j in range(K):
        prob[j] /= s
        logp[j] -= lse


@njit(**_STEP)
def transition_step(W, phi, trans, log_trans):
    """trans[i, j] = p(rho_t = j | rho_{t-1} = i, phi_t) and its log, (K, K)."""
    K = W.shape[1]
    for i in range(K):
        softmax_step(W[i + 1], phi, trans[i], log_trans[i])


@njit(**_STEP)
def condition_step(alpha_prev, trans, log_trans, log_emis, alpha_out, log_alpha_out):
    """One forward step: predict with the transitions, condition on the step's
    emission, normalise.  Returns (log normaliser, fast): -inf for an impossible
    step; fast is False when the step had to be redone in log space.
    ``log_alpha_out`` is scratch space for that fallback.

    Works with probabilities scaled by the largest emission (one exp per
    phase); where that underflows it redoes the step exactly in log space.
    """
    K = log_emis.shape[0]
    mx = -np.inf
    for j in range(K):
        if log_emis[j] > mx:
            mx = log_emis[j]
    if mx == -np.inf:
        return -np.inf, True
    z = 0.0
    for j in range(K):
        pred = 0.0
        for i in range(K):
            pred += alpha_prev[i] * trans[i, j]
        a = pred * math.exp(log_emis[j] - mx)
        alpha_out[j] = a
        z += a
    if z > 1e-250:
        for j in range(K):
            alpha_out[j] /= z
        return mx + math.log(z), True
    for j in range(K):
        best = -np.inf
        for i in range(K):
            if alpha_prev[i] > 0.0:
                v = math.log(alpha_prev[i]) + log_trans[i, j]
                if v > best:
                    best = v
        if best == -np.inf:
            log_alpha_out[j] = -np.inf
        else:
            acc = 0.0
            for i in range(K):
                if alpha_prev[i] > 0.0:
                    acc += math.exp(math.log(alpha_prev[i]) + log_trans[i, j] - best)
            log_alpha_out[j] = best + math.log(acc) + log_emis[j]
    return _normalise(log_alpha_out, alpha_out), False


@njit(**_STEP)
def initial_condition_step(log_initial, log_emis, alpha_out, log_alpha_out):
    """The first forward step: prior of rho_0 times its emission, normalised."""
    K = log_emis.shape[0]
    for j in range(K):
        log_alpha_out[j] = log_initial[j] + log_emis[j]
    return _normalise(log_alpha_out, alpha_out)


@njit(**_STEP)
def _normalise(log_a, a):
    c = logsumexp(log_a)
    K = log_a.shape[0]
    if c == -np.inf or not math.isfinite(c):
        for j in range(K):
            a[j] = np.nan
        return c
    for j in range(K):
        log_a[j] -= c
        a[j] = math.exp(log_a[j])
    return c


# --------------------------------------------------------------------------
# batch arrays for one demonstration
# --------------------------------------------------------------------------


@njit(**_JIT)
def log_emissions(regressors, next_states, C, chol_inv, log_norm):
    """(T-1, K) log-likelihood of every step under every phase."""
    N = regressors.shape[0]
    K, n, _ = C.shape
    out = np.empty((N, K))
    r = np.empty(n)
    for t in range(N):
        emission_step(next_states[t], regressors[t], C, chol_inv, log_norm, r, out[t])
    return out


@njit(**_JIT)
def initial_and_transitions_into(features, W, log_initial, trans, log_trans):
    """Write log p(rho_0 | phi_0) (K,) and the time-varying transitions
    (T-1, K, K) as probabilities and logs (row 0 unused, set to zero)."""
    N = features.shape[0]
    K = W.shape[1]
    prob0 = np.empty(K)
    softmax_step(W[0], features[0], prob0, log_initial)
    trans[0] = 0.0
    log_trans[0] = 0.0
    for t in range(1, N):
        transition_step(W, features[t], trans[t], log_trans[t])


@njit(**_JIT)
def initial_and_transitions(features, W):
    """(log_initial (K,), trans (T-1, K, K), log_trans (T-1, K, K)) of one demonstration."""
    N = features.shape[0]
    K = W.shape[1]
    log_initial = np.empty(K)
    trans = np.empty((N, K, K))
    log_trans = np.empty((N, K, K))
    initial_and_transitions_into(features, W, log_initial, trans, log_trans)
    return log_initial, trans, log_trans


# --------------------------------------------------------------------------
# forward, backward, smoother, Viterbi
# --------------------------------------------------------------------------


@njit(**_JIT)
def forward(log_initial, trans, log_trans, log_emis):
    """Normalised forward messages (T-1, K) and per-step log normalisers (T-1,).

    alpha[t, j] = p(rho_t = j | samples 0..t+1); the log-likelihood of the
    demonstration is ``log_c.sum()``.  Runs on scaled probabilities; if any
    step underflows there, the whole demonstration is redone in log space.
    """
    N, K = log_emis.shape
    alpha = np.empty((N, K))
    la = np.empty(K)
    log_c = np.empty(N)
    log_c[0] = initial_condition_step(log_initial, log_emis[0], alpha[0], la)
    for t in range(1, N):
        c, fast = condition_step(alpha[t - 1], trans[t], log_trans[t], log_emis[t], alpha[t], la)
        log_c[t] = c
        if not fast:
            log_alpha, log_c = forward_log(log_initial, log_trans, log_emis)
            return np.exp(log_alpha), log_c
        if c == -np.inf:
            for s in range(t + 1, N):
                log_c[s] = -np.inf
                for j in range(K):
                    alpha[s, j] = np.nan
            break
    return alpha, log_c


@njit(**_JIT)
def forward_log(log_initial, log_trans, log_emis):
    """The forward pass entirely in log space: normalised log messages (T-1, K)
    and log normalisers (T-1,).  Exact where probabilities would underflow."""
    N, K = log_emis.shape
    la = np.empty((N, K))
    log_c = np.empty(N)
    tmp = np.empty(K)
    for j in range(K):
        la[0, j] = log_initial[j] + log_emis[0, j]
    log_c[0] = logsumexp(la[0])
    for j in range(K):
        la[0, j] -= log_c[0]
    for t in range(1, N):
        for j in range(K):
            for i in range(K):
                tmp[i] = la[t - 1, i] + log_trans[t, i, j]
            la[t, j] = log_emis[t, j] + logsumexp(tmp)
        log_c[t] = logsumexp(la[t])
        if log_c[t] == -np.inf:
            for s in range(t, N):
                log_c[s] = -np.inf
                for j in range(K):
                    la[s, j] = np.nan
            break
        for j in range(K):
            la[t, j] -= log_c[t]
    return la, log_c


@njit(**_JIT)
def smoother_log_into(log_initial, log_trans, log_emis, gamma, xi):
    """Forward-backward entirely in log space (the exact slow path of
    ``smoother_into``); same outputs and return value."""
    N, K = log_emis.shape
    la, log_c = forward_log(log_initial, log_trans, log_emis)
    loglik = 0.0
    for t in range(N):
        loglik += log_c[t]
    if loglik == -np.inf:
        gamma[:, :] = np.nan
        xi[:, :, :] = np.nan
        return loglik
    lb = np.zeros(K)
    nb = np.empty(K)
    tmp = np.empty(K)
    tmp2 = np.empty(K * K)
    for t in range(N - 1, -1, -1):
        for j in range(K):
            tmp[j] = la[t, j] + lb[j]
        c = logsumexp(tmp)
        for j in range(K):
            gamma[t, j] = math.exp(tmp[j] - c)
        if t == 0:
            for i in range(K):
                for j in range(K):
                    xi[0, i, j] = 0.0
            break
        for i in range(K):
            for j in range(K):
                tmp2[i * K + j] = la[t - 1, i] + log_trans[t, i, j] + log_emis[t, j] + lb[j]
        c = logsumexp(tmp2)
        for i in range(K):
            for j in range(K):
                xi[t, i, j] = math.exp(tmp2[i * K + j] - c)
        for i in range(K):
            for j in range(K):
                tmp[j] = log_trans[t, i, j] + log_emis[t, j] + lb[j]
            nb[i] = logsumexp(tmp) - log_c[t]
        for i in range(K):
            lb[i] = nb[i]
    return loglik


@njit(**_JIT)
def smoother_into(log_initial, trans, log_trans, log_emis, gamma, xi):
    """Forward-backward for one demonstration, writing gamma (T-1, K) and
    xi (T-1, K, K) (xi[t, i, j] = p(rho_{t-1}=i, rho_t=j | demo); xi[0] = 0).
    Returns the log-likelihood; -inf (and NaN posteriors) when impossible.

    Runs on scaled probabilities (backward messages rescaled to max 1 at every
    step: the scale cancels in the normalised gamma and xi); if any
    normaliser underflows there, the demonstration is redone in log space.
    """
    N, K = log_emis.shape
    alpha = np.empty((N, K))
    la = np.empty(K)
    loglik = initial_condition_step(log_initial, log_emis[0], alpha[0], la)
    for t in range(1, N):
        c, fast = condition_step(alpha[t - 1], trans[t], log_trans[t], log_emis[t], alpha[t], la)
        if not fast or c == -np.inf:
            return smoother_log_into(log_initial, log_trans, log_emis, gamma, xi)
        loglik += c
    if not math.isfinite(loglik):
        return smoother_log_into(log_initial, log_trans, log_emis, gamma, xi)
    beta = np.ones(K)
    e = np.empty(K)
    nb = np.empty(K)
    for t in range(N - 1, -1, -1):
        s = 0.0
        for j in range(K):
            g = alpha[t, j] * beta[j]
            gamma[t, j] = g
            s += g
        if not s > 1e-250:
            return smoother_log_into(log_initial, log_trans, log_emis, gamma, xi)
        for j in range(K):
            gamma[t, j] /= s
        if t == 0:
            for i in range(K):
                for j in range(K):
                    xi[0, i, j] = 0.0
            break
        mx = -np.inf
        for j in range(K):
            if log_emis[t, j] > mx:
                mx = log_emis[t, j]
        for j in range(K):
            e[j] = math.exp(log_emis[t, j] - mx) * beta[j]
        s = 0.0
        bmax = 0.0
        for i in range(K):
            acc = 0.0
            for j in range(K):
                v = alpha[t - 1, i] * trans[t, i, j] * e[j]
                xi[t, i, j] = v
                s += v
                acc += trans[t, i, j] * e[j]
            nb[i] = acc
            if acc > bmax:
                bmax = acc
        if not (s > 1e-250 and bmax > 1e-250):
            return smoother_log_into(log_initial, log_trans, log_emis, gamma, xi)
        for i in range(K):
            for j in range(K):
                xi[t, i, j] /= s
        for i in range(K):
            beta[i] = nb[i] / bmax
    return loglik


@njit(**_JIT)
def smoother(log_initial, trans, log_trans, log_emis):
    """(log-likelihood, gamma (T-1, K), xi (T-1, K, K)) of one demonstration."""
    N, K = log_emis.shape
    gamma = np.empty((N, K))
    xi = np.empty((N, K, K))
    ll = smoother_into(log_initial, trans, log_trans, log_emis, gamma, xi)
    return ll, gamma, xi


@njit(**_JIT)
def viterbi(log_initial, log_trans, log_emis):
    """Most likely phase path (T-1,) and its joint log-probability."""
    N, K = log_emis.shape
    delta = np.empty(K)
    new = np.empty(K)
    back = np.zeros((N, K), dtype=np.int64)
    for j in range(K):
        delta[j] = log_initial[j] + log_emis[0, j]
    for t in range(1, N):
        for j in range(K):
            best = -np.inf
            arg = 0
            for i in range(K):
                v = delta[i] + log_trans[t, i, j]
                if v > best:
                    best = v
                    arg = i
            new[j] = best + log_emis[t, j]
            back[t, j] = arg
        for j in range(K):
            delta[j] = new[j]
    path = np.empty(N, dtype=np.int64)
    best = -np.inf
    arg = 0
    for j in range(K):
        if delta[j] > best:
            best = delta[j]
            arg = j
    path[N - 1] = arg
    for t in range(N - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path, best


# --------------------------------------------------------------------------
# E-step over stacked demonstrations (parallel across demonstrations)
# --------------------------------------------------------------------------


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def e_step_stacked(regressors, next_states, features, starts, C, chol_inv, log_norm, W):
    """E-step over stacked demonstrations, in parallel across demonstrations.

    Returns the log-likelihood per demonstration (D,), gamma (N, K), xi (N, K, K)
    and the transitions the posteriors were computed with, trans and log_trans
    (N, K, K), which the M-step reuses to score the current W.
    """
    N = regressors.shape[0]
    K = C.shape[0]
    D = starts.shape[0] - 1
    gamma = np.empty((N, K))
    xi = np.empty((N, K, K))
    trans = np.empty((N, K, K))
    log_trans = np.empty((N, K, K))
    ll = np.empty(D)
    for d in prange(D):
        a, b = starts[d], starts[d + 1]
        le = log_emissions(regressors[a:b], next_states[a:b], C, chol_inv, log_norm)
        li = np.empty(K)
        initial_and_transitions_into(features[a:b], W, li, trans[a:b], log_trans[a:b])
        ll[d] = smoother_into(li, trans[a:b], log_trans[a:b], le, gamma[a:b], xi[a:b])
    return ll, gamma, xi, trans, log_trans


# --------------------------------------------------------------------------
# the online filter's update: one compiled call per sample
# --------------------------------------------------------------------------


@njit(**_JIT)
def features_step(state, force, goal, use_state_features, out):
    """phi = [force; 1] (ETAR) or [state - goal; 1] (STAR)."""
    if use_state_features:
        d = state.shape[0]
        for a in range(d):
            out[a] = state[a] - goal[a]
        out[d] = 1.0
    else:
        d = force.shape[0]
        for a in range(d):
            out[a] = force[a]
        out[d] = 1.0


@njit(**_JIT)
def filter_update(state, force, goal, use_state_features, prev_state, prev_force, flags,
                  alpha, log_alpha, C, chol_inv, log_norm, W, x, phi, r, log_emis, trans,
                  log_trans, new_alpha, new_log_alpha):
    """Advance the online forward filter by one sample; returns a status code.

    Status: 0 ok; 1 input not finite; 2 the sample is impossible under every
    phase.  On 1 and 2 the filter state is left unchanged.  ``flags`` (2,) bool:
    [has a previous sample, the first phase has been conditioned].  On the very
    first sample only the prior of rho_0 can be formed and ``alpha`` gets it.
    """
    n = state.shape[0]
    m = force.shape[0]
    K = alpha.shape[0]
    for a in range(n):
        if not math.isfinite(state[a]):
            return 1
    for a in range(m):
        if not math.isfinite(force[a]):
            return 1
    if not flags[0]:
        features_step(state, force, goal, use_state_features, phi)
        softmax_step(W[0], phi, alpha, log_alpha)
        flags[0] = True
    else:
        # the step prev -> current is governed by the previous sample's phase
        for a in range(n):
            x[a] = prev_state[a]
        for a in range(m):
            x[n + a] = prev_force[a]
        x[n + m] = 1.0
        features_step(prev_state, prev_force, goal, use_state_features, phi)
        emission_step(state, x, C, chol_inv, log_norm, r, log_emis)
        if not flags[1]:
            c = initial_condition_step(log_alpha, log_emis, new_alpha, new_log_alpha)
        else:
            transition_step(W, phi, trans, log_trans)
            c, _ = condition_step(alpha, trans, log_trans, log_emis, new_alpha, new_log_alpha)
        if not math.isfinite(c):
            return 2
        flags[1] = True
        for j in range(K):
            alpha[j] = new_alpha[j]
            log_alpha[j] = new_log_alpha[j]
    for a in range(n):
        prev_state[a] = state[a]
    for a in range(m):
        prev_force[a] = force[a]
    return 0
