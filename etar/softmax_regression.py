"""The softmax-regression objective of EM's M-step for the transition weights W.

Fitting W is a weighted multinomial logistic regression per weight block: the
targets are the E-step's expected transitions xi (for W[0], gamma at each
demonstration's first step), the inputs the transition features phi_t.  These kernels give its value and
gradient (``etar.em`` hands them to its solver); they are compiled with numba and
parallel over fixed chunks of steps, so the sums are the same on any thread count.

Shapes as in ``etar.inference``: ``w`` (R, K, d+1) weight blocks, ``features``
(N, d+1), ``targets`` (N, R, K).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from kernel_plumbing.addresses import JIT as _JIT


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def softmax_regression_objective(w, features, targets, l2):
    """Weighted cross-entropy of several weight blocks and their gradients.

    For every block r: f_r(w_r) = -sum_t sum_j targets[t, r, j] log softmax(w_r phi_t)_j
    + l2/2 |w_r|^2 and grad_r = sum_t phi_t (q_t softmax(w_r phi_t) - targets[t, r])^T
    with q_t = sum_j targets[t, r, j] (thesis eq. 67: G = F (P - L)).
    w (R, K, d+1), features (N, d+1), targets (N, R, K) -> values (R,), grads (R, K, d+1).
    Steps with zero target mass are skipped.  The blocks are independent
    problems sharing the features, so one pass serves all of them.
    """
    R, K, d1 = w.shape
    N = features.shape[0]
    n_chunks = 8
    vals = np.zeros((n_chunks, R))
    grads = np.zeros((n_chunks, R, K, d1))
    for c in prange(n_chunks):
        lo = c * N // n_chunks
        hi = (c + 1) * N // n_chunks
        logits = np.empty(K)
        ex = np.empty(K)
        for rr in range(R):
            v = 0.0
            g = np.zeros((K, d1))
            for t in range(lo, hi):
                q = 0.0
                for j in range(K):
                    q += targets[t, rr, j]
                if q == 0.0:
                    continue
                mx = -np.inf
                for j in range(K):
                    acc = 0.0
                    for f in range(d1):
                        acc += w[rr, j, f] * features[t, f]
                    logits[j] = acc
                    if acc > mx:
                        mx = acc
                ssum = 0.0
                for j in range(K):
                    e = math.exp(logits[j] - mx)
                    ex[j] = e
                    ssum += e
                lse = mx + math.log(ssum)
                for j in range(K):
                    tj = targets[t, rr, j]
                    if tj != 0.0:
                        v -= tj * (logits[j] - lse)
                    gj = q * (ex[j] / ssum) - tj
                    for f in range(d1):
                        g[j, f] += gj * features[t, f]
            vals[c, rr] = v
            grads[c, rr] = g
    return _reduce_chunks(vals, grads, w, l2)


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def softmax_regression_at(w, features, targets, trans, log_trans, l2):
    """``softmax_regression_objective`` at the weights the E-step just used,
    from its transitions (trans[t, r] = softmax(w_r phi_t)): no exponentials."""
    R, K, d1 = w.shape
    N = features.shape[0]
    n_chunks = 8
    vals = np.zeros((n_chunks, R))
    grads = np.zeros((n_chunks, R, K, d1))
    for c in prange(n_chunks):
        lo = c * N // n_chunks
        hi = (c + 1) * N // n_chunks
        for rr in range(R):
            v = 0.0
            g = np.zeros((K, d1))
            for t in range(lo, hi):
                q = 0.0
                for j in range(K):
                    q += targets[t, rr, j]
                if q == 0.0:
                    continue
                for j in range(K):
                    tj = targets[t, rr, j]
                    if tj != 0.0:
                        v -= tj * log_trans[t, rr, j]
                    gj = q * trans[t, rr, j] - tj
                    for f in range(d1):
                        g[j, f] += gj * features[t, f]
            vals[c, rr] = v
            grads[c, rr] = g
    return _reduce_chunks(vals, grads, w, l2)


@njit(**_JIT)
def _reduce_chunks(vals, grads, w, l2):
    n_chunks, R = vals.shape
    K, d1 = w.shape[1], w.shape[2]
    values = np.zeros(R)
    grad = np.zeros((R, K, d1))
    for c in range(n_chunks):
        for rr in range(R):
            values[rr] += vals[c, rr]
            for j in range(K):
                for f in range(d1):
                    grad[rr, j, f] += grads[c, rr, j, f]
    for rr in range(R):
        for j in range(K):
            for f in range(d1):
                values[rr] += 0.5 * l2 * w[rr, j, f] * w[rr, j, f]
                grad[rr, j, f] += l2 * w[rr, j, f]
    return values, grad
