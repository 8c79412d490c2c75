"""Brute-force ETAR inference by enumerating every phase path (tiny problems only)."""

import itertools

import numpy as np
from scipy.special import logsumexp
from scipy.stats import multivariate_normal


def log_softmax(z):
    return z - logsumexp(z)


def path_log_probs(model, states, forces):
    """{path: log p(path, states | forces)} for every path of T-1 phases."""
    A, B, S, W = model.A, model.B, model.Sigma, model.W
    K = A.shape[0]
    T = states.shape[0]
    if model.transitions == "effect":
        phi = np.hstack([forces, np.ones((T, 1))])
    else:
        phi = np.hstack([states - states[-1], np.ones((T, 1))])
    u = np.hstack([forces, np.ones((T, 1))])
    le = np.array([[multivariate_normal.logpdf(states[t + 1], A[j] @ states[t] + B[j] @ u[t], S[j])
                    for j in range(K)] for t in range(T - 1)])
    out = {}
    for path in itertools.product(range(K), repeat=T - 1):
        lp = log_softmax(W[0] @ phi[0])[path[0]] + le[0, path[0]]
        for t in range(1, T - 1):
            lp += log_softmax(W[path[t - 1] + 1] @ phi[t])[path[t]] + le[t, path[t]]
        out[path] = lp
    return out


def brute_force(model, states, forces):
    """(log-likelihood, gamma (T-1, K), xi (T-1, K, K) with xi[0] = 0, Viterbi path,
    filtered (T-1, K): p(rho_t | samples 0..t+1))."""
    paths = path_log_probs(model, states, forces)
    K = model.A.shape[0]
    N = states.shape[0] - 1
    keys = list(paths)
    lps = np.array([paths[k] for k in keys])
    ll = logsumexp(lps)
    post = np.exp(lps - ll)
    P = np.array(keys)
    gamma = np.zeros((N, K))
    xi = np.zeros((N, K, K))
    for t in range(N):
        np.add.at(gamma[t], P[:, t], post)
        if t:
            np.add.at(xi[t], (P[:, t - 1], P[:, t]), post)
    best = keys[int(np.argmax(lps))]
    # filtered: marginalise paths of the prefix; the prefix' joint is the sum over
    # suffixes only up to the suffix likelihood, so recompute on truncated data
    filtered = np.zeros((N, K))
    for t in range(N):
        sub = path_log_probs(model, states[: t + 2], forces[: t + 2]) if model.transitions == "effect" else None
        if sub is None:
            break
        sk = list(sub)
        sl = np.array([sub[k] for k in sk])
        w = np.exp(sl - logsumexp(sl))
        np.add.at(filtered[t], np.array(sk)[:, t], w)
    return ll, gamma, xi, np.array(best), filtered
