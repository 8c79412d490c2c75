"""The softmax-regression objective of EM's M-step for the transition weights W.

Fitting W is a weighted multinomial logistic regression per weight block: the
targets are the E-step's expected transitions xi (for W[0], gamma at each
demonstration's first step), the inputs the transition features phi_t.  These kernels give its value and
gradient (``etar.em`` hands them to its solver); they are compiled with numba and
parallel over fixed chunks of steps, so the sums are the same on any thread count.
``preconditioned_steps`` is that solver's descent compiled, bit for bit the numpy one in
``etar.em`` (which checks it once per process and keeps its own where it differs): learning
runs it several hundred times a fit, and numpy's per-call cost was half of a small fit's time.

Shapes as in ``etar.inference``: ``w`` (R, K, d+1) weight blocks, ``features``
(N, d+1), ``targets`` (N, R, K).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from kernel_plumbing import blas
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
    vals = np.zeros((_CHUNKS, R))
    grads = np.zeros((_CHUNKS, R, K, d1))
    for c in prange(_CHUNKS):
        _objective_chunk(w, features, targets, c, vals, grads)
    return _reduce_chunks(vals, grads, w, l2)


@njit(**_JIT)
def _objective_serial(w, features, targets, l2):
    """``softmax_regression_objective`` on this thread, chunk after chunk: the same sums, for
    the compiled descent (with the parallel one called from inside that kernel, 1 Ctrl-C in
    16 under load hung ``etar learn`` there for good; none in 16 with this one)."""
    R, K, d1 = w.shape
    vals = np.zeros((_CHUNKS, R))
    grads = np.zeros((_CHUNKS, R, K, d1))
    for c in range(_CHUNKS):
        _objective_chunk(w, features, targets, c, vals, grads)
    return _reduce_chunks(vals, grads, w, l2)


_CHUNKS = 8  # fixed, so the sums are the same on any number of threads


@njit(**_JIT)
def _objective_chunk(w, features, targets, c, vals, grads):
    """Chunk ``c`` of the steps: each block's value and gradient over it, into vals[c], grads[c]."""
    R, K, d1 = w.shape
    N = features.shape[0]
    lo = c * N // _CHUNKS
    hi = (c + 1) * N // _CHUNKS
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


@njit(**_JIT)
def preconditioned_steps(w, features, targets, l2, factors, value, grad, max_steps, gesv, dot):
    """``etar.em.fit_softmax_blocks``' descent (solver "gd") after its set-up, compiled: the
    same operations in the same order, its solves and dot products through the functions
    numpy calls (``kernel_plumbing.blas``: dgesv at ``gesv`` on column-major copies, as numpy's
    solve makes them; ddot at ``dot``), so the same bits.  Updates ``w``, ``value`` and
    ``grad`` in place; returns LAPACK's info of the first solve that failed (0: none did, and
    then the update is whole)."""
    R, K, d1 = w.shape
    n = K * d1
    lu = np.empty((n, n))
    rhs = np.empty(n)
    ints = np.array([n, 1, n, n, 0], dtype=np.int64)  # n, nrhs, lda, ldb, info
    ipiv = np.zeros(n, dtype=np.int64)
    at = ints.ctypes.data
    active = np.ones(R, dtype=np.bool_)
    accepted = np.zeros(R, dtype=np.bool_)
    step = np.zeros(R)
    slope = np.zeros(R)
    direction = np.zeros((R, K, d1))
    cand_w = np.empty_like(w)
    cv = np.empty(R)
    cg = np.empty_like(grad)
    for _ in range(max_steps):
        direction[:] = 0.0
        slope[:] = 0.0
        for r in range(R):
            if not active[r]:
                continue
            # L y = grad_r, then L^T d = y: numpy's solve copies A column-major, so L^T's
            # copy is L's rows as they are and L's copy its transpose
            L = factors[r]
            for i in range(n):
                for k in range(n):
                    lu[k, i] = L[i, k]
            g = grad[r].ravel()
            for i in range(n):
                rhs[i] = g[i]
            blas.call_gesv(gesv, at, at + 8, lu.ctypes.data, at + 16, ipiv.ctypes.data, rhs.ctypes.data, at + 24, at + 32)
            if ints[4] != 0:
                return ints[4]
            lu[:] = L
            blas.call_gesv(gesv, at, at + 8, lu.ctypes.data, at + 16, ipiv.ctypes.data, rhs.ctypes.data, at + 24, at + 32)
            if ints[4] != 0:
                return ints[4]
            d = direction[r].ravel()
            for i in range(n):
                d[i] = rhs[i]
            slope[r] = blas.call_dot(dot, n, g.ctypes.data, 1, d.ctypes.data, 1)
            if slope[r] <= 1e-14 * max(1.0, abs(value[r])):
                active[r] = False
        if not active.any():
            break
        for r in range(R):
            step[r] = 1.0 if active[r] else 0.0
            accepted[r] = not active[r]
        cand_w[:] = w
        for _ in range(40):  # Armijo backtracking, per block
            for r in range(R):
                if not accepted[r]:
                    cand_w[r] = w[r] - step[r] * direction[r]
            cv, cg = _objective_serial(cand_w, features, targets, l2)
            done = True
            for r in range(R):
                if not accepted[r] and cv[r] <= value[r] - 1e-4 * step[r] * slope[r]:
                    accepted[r] = True
                done = done and accepted[r]
            if done:
                break
            for r in range(R):
                if not accepted[r]:
                    step[r] *= 0.5
        any_active = False
        for r in range(R):
            keep = accepted[r] and active[r]
            gain = value[r] - cv[r] if keep else 0.0
            if keep:
                w[r] = cand_w[r]
                value[r] = cv[r]
                grad[r] = cg[r]
            active[r] = keep and gain > 1e-11 * max(1.0, abs(value[r]))
            any_active = any_active or active[r]
        if not any_active:
            break
    return 0


@njit(**_JIT)
def bohning_factors(features, q, l2, K, gemm, potrf):
    """``etar.em._bohning_factors`` compiled, for ``q`` = targets.sum(axis=2) (N, R): the same
    operations in the same order, ``features.T @ (features * q_r)`` by the dgemm numpy's
    matmul calls (row-major, the first transposed) and the Cholesky factor by its dpotrf on
    a column-major copy, lower, the upper triangle zero; the trace summed in order, as numpy
    sums fewer than 8 numbers.  Returns (factors (R, K(d+1), K(d+1)), LAPACK's info of the
    first factorisation that failed, or 0)."""
    N, d1 = features.shape
    R = q.shape[1]
    n = K * d1
    factors = np.zeros((R, n, n))
    S = np.empty((d1, d1))
    X = np.empty((N, d1))
    buf = np.empty((n, n))
    ints = np.array([n, n, 0], dtype=np.int64)  # n, lda, info
    uplo = np.array([76], dtype=np.uint8)  # 'L'
    at = ints.ctypes.data
    c = 1.0 / (K + 1)
    for r in range(R):
        for t in range(N):
            for f in range(d1):
                X[t, f] = features[t, f] * q[t, r]
        blas.call_gemm(gemm, np.int32(blas.ROW_MAJOR), np.int32(blas.TRANS), np.int32(blas.NO_TRANS), d1, d1, N, 1.0,
                       features.ctypes.data, d1, X.ctypes.data, d1, 0.0, S.ctypes.data, d1)
        trace = S[0, 0]
        for i in range(1, d1):
            trace += S[i, i]
        floor = 1e-12 * (trace + 1.0)
        ridge = floor if floor > l2 else l2
        for a in range(K):
            for b in range(K):
                weight = 0.5 * ((1.0 if a == b else 0.0) - c)
                for i in range(d1):
                    for j in range(d1):
                        row, col = a * d1 + i, b * d1 + j
                        buf[col, row] = weight * S[i, j] + ridge * (1.0 if row == col else 0.0)
        blas.call_potrf(potrf, uplo.ctypes.data, at, buf.ctypes.data, at + 8, at + 16)
        if ints[2] != 0:
            return factors, ints[2]
        for i in range(n):
            for j in range(i + 1):
                factors[r, i, j] = buf[j, i]
    return factors, 0
