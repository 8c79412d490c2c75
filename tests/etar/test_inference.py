"""Inference against brute-force enumeration of every phase path, and stress cases."""

import numpy as np
import pytest

from etar import ETAR, inference
from tests.etar.oracle import brute_force


def random_model(rng, K, n, m, transitions="effect", scale=1.0):
    model = ETAR(K, transitions)
    d = n if transitions == "state" else m
    model.A = np.eye(n)[None] + 0.1 * rng.normal(size=(K, n, n))
    model.B = 0.3 * rng.normal(size=(K, n, m + 1))
    L = 0.3 * rng.normal(size=(K, n, n)) + np.eye(n)[None]
    model.Sigma = scale * (L @ L.transpose(0, 2, 1) + 0.1 * np.eye(n)[None])
    model.W = 2.0 * rng.normal(size=(K + 1, K, d + 1))
    return model


def random_demo(rng, T, n, m, scale=1.0):
    states = np.cumsum(scale * rng.normal(size=(T, n)), axis=0)
    forces = 3.0 * rng.normal(size=(T, m))
    return states, forces


def batch(model, s, f):
    li, tr, lt, le = model._inference_arrays(s, f)
    ll, gamma, xi = inference.smoother(li, tr, lt, le)
    alpha, log_c = inference.forward(li, tr, lt, le)
    path, best = inference.viterbi(li, lt, le)
    return ll, gamma, xi, path, best, alpha, log_c


@pytest.mark.parametrize("K,n,m,T", [(2, 2, 1, 6), (3, 2, 2, 5), (3, 1, 3, 6), (4, 2, 1, 4)])
def test_matches_brute_force(rng, K, n, m, T):
    for _ in range(3):
        model = random_model(rng, K, n, m)
        s, f = random_demo(rng, T, n, m)
        ll_bf, gamma_bf, xi_bf, path_bf, filtered_bf = brute_force(model, s, f)
        ll, gamma, xi, path, best, alpha, log_c = batch(model, s, f)
        assert ll == pytest.approx(ll_bf, rel=1e-10, abs=1e-9)
        assert model.log_likelihood([(s, f)]) == pytest.approx(ll_bf, rel=1e-10, abs=1e-9)
        np.testing.assert_allclose(gamma, gamma_bf, atol=1e-10)
        np.testing.assert_allclose(xi, xi_bf, atol=1e-10)
        np.testing.assert_array_equal(path, path_bf)
        np.testing.assert_allclose(alpha, filtered_bf, atol=1e-10)
        np.testing.assert_array_equal(model.viterbi(s, f), path_bf)
        np.testing.assert_allclose(model.posterior(s, f), gamma_bf, atol=1e-10)


def test_star_matches_brute_force(rng):
    model = random_model(rng, 3, 2, 2, transitions="state")
    s, f = random_demo(rng, 5, 2, 2)
    ll_bf, gamma_bf, xi_bf, path_bf, _ = brute_force(model, s, f)
    ll, gamma, xi, path, *_ = batch(model, s, f)
    assert ll == pytest.approx(ll_bf, rel=1e-10)
    np.testing.assert_allclose(gamma, gamma_bf, atol=1e-10)
    np.testing.assert_array_equal(path, path_bf)


def test_near_forbidden_transitions_use_exact_log_space(rng):
    """Transitions of probability ~e^-760 underflow as products of probabilities;
    the log-space fallback must still agree with enumeration."""
    K, n, m, T = 3, 1, 1, 6
    model = random_model(rng, K, n, m)
    model.W[1:, :, -1] = 0.0
    model.W[1:, :, 0] = 0.0
    # from phase 0 nothing but phase 0 is plausible ...
    model.W[1, 1:, -1] = -760.0
    # ... but phase 0 explains the data terribly after step 2
    s, f = random_demo(rng, T, n, m)
    model.A[0] = 1.0
    model.B[0] = 0.0
    model.Sigma[0] = 1e-6
    model.W[0, 0, -1] = 50.0
    ll_bf, gamma_bf, xi_bf, path_bf, filtered_bf = brute_force(model, s, f)
    assert np.isfinite(ll_bf)
    ll, gamma, xi, path, best, alpha, _ = batch(model, s, f)
    assert ll == pytest.approx(ll_bf, rel=1e-9)
    np.testing.assert_allclose(gamma, gamma_bf, atol=1e-9)
    np.testing.assert_allclose(xi, xi_bf, atol=1e-9)
    np.testing.assert_allclose(alpha, filtered_bf, atol=1e-9)
    np.testing.assert_array_equal(path, path_bf)


def test_impossible_demonstration_is_minus_inf_not_nan(rng):
    model = random_model(rng, 2, 1, 1)
    model.Sigma[:] = 1e-300  # nothing moves under any phase
    s, f = random_demo(rng, 6, 1, 1)
    ll = model.log_likelihood([(s, f)])
    assert ll == -np.inf or ll < -1e250
    assert not np.isnan(ll)


def test_stress_long_many_phases_large_scale_stays_finite_and_normalised(rng):
    K, n, m, T = 6, 3, 3, 20000
    model = random_model(rng, K, n, m, scale=1e4)
    model.W *= 20.0  # very peaked transitions
    s, f = random_demo(rng, T, n, m, scale=100.0)
    ll, gamma, xi, path, best, alpha, log_c = batch(model, s, f)
    assert np.isfinite(ll) and np.isfinite(best)
    assert np.all(np.isfinite(gamma)) and np.all(np.isfinite(xi)) and np.all(np.isfinite(alpha))
    np.testing.assert_allclose(gamma.sum(axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(alpha.sum(axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(xi[1:].sum(axis=(1, 2)), 1.0, atol=1e-9)
    # pairwise marginals are consistent with the single-step ones
    np.testing.assert_allclose(xi[1:].sum(axis=1), gamma[1:], atol=1e-8)
    np.testing.assert_allclose(xi[1:].sum(axis=2), gamma[:-1], atol=1e-8)
    assert ll == pytest.approx(log_c.sum())


def test_online_filter_equals_batch_forward_pass(rng):
    model = random_model(rng, 3, 3, 3)
    s, f = random_demo(rng, 400, 3, 3)
    filt = model.filter()
    first = filt.update(s[0], f[0])
    # before any step only the prior of the first phase is known
    phi0 = np.append(f[0], 1.0)
    prior = np.exp(model.W[0] @ phi0 - np.logaddexp.reduce(model.W[0] @ phi0))
    np.testing.assert_allclose(first, prior, atol=1e-12)
    online = np.array([filt.update(s[t], f[t]) for t in range(1, len(s))])
    _, _, _, _, _, alpha, _ = batch(model, s, f)
    np.testing.assert_allclose(online, alpha, atol=1e-12)
    assert filt.n_updates == len(s)


def test_online_filter_rejects_nan_and_keeps_its_state(rng):
    model = random_model(rng, 3, 2, 2)
    s, f = random_demo(rng, 50, 2, 2)
    ref = model.filter()
    filt = model.filter()
    for t in range(20):
        expected = ref.update(s[t], f[t])
        filt.update(s[t], f[t])
    bad = f[20].copy()
    bad[1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        filt.update(s[20], bad)
    with pytest.raises(ValueError, match="expects state"):
        filt.update(s[20][:1], f[20])
    for t in range(20, 50):
        expected = ref.update(s[t], f[t])
        np.testing.assert_array_equal(filt.update(s[t], f[t]), expected)


def test_a_held_stretch_is_not_conditioned_on_and_the_filter_continues_from_before_it(rng):
    """``anchor`` (the KRC held the arm, or a sample is missing): the posterior stays,
    and the next update conditions on the step from the anchored sample only."""
    model = random_model(rng, 3, 3, 3)
    s, f = random_demo(rng, 60, 3, 3)
    filt = model.filter()
    np.testing.assert_array_equal(filt.anchor(s[0], f[0]), model.filter().update(s[0], f[0]))  # first: the prior
    for t in range(1, 20):
        before = filt.update(s[t], f[t])
    for t in range(20, 30):
        np.testing.assert_array_equal(filt.anchor(s[t], f[t]), before)
    with pytest.raises(ValueError, match="non-finite"):
        filt.anchor(s[30], np.full(3, np.nan))
    online = np.array([filt.update(s[t], f[t]) for t in range(30, 60)])
    # the forward recursion from `before` over the steps 29->30 ... 58->59 (row t of the
    # arrays of samples 28.. is the step 28+t -> 29+t, under the transition at sample 28+t)
    _, trans, _, log_emis = model._inference_arrays(s[28:], f[28:])
    alpha, expected = before, []
    for t in range(1, 31):
        a = (alpha @ trans[t]) * np.exp(log_emis[t] - log_emis[t].max())
        alpha = a / a.sum()
        expected.append(alpha)
    np.testing.assert_allclose(online, expected, atol=1e-12)
    # conditioning on the held steps instead gives another posterior
    plain = model.filter()
    for t in range(31):
        last = plain.update(s[t], f[t])
    assert np.abs(last - online[0]).max() > 1e-6


def test_star_filter_needs_a_goal(rng):
    model = random_model(rng, 2, 2, 2, transitions="state")
    with pytest.raises(ValueError, match="goal"):
        model.filter()
    s, f = random_demo(rng, 30, 2, 2)
    filt = model.filter(goal=s[-1])
    online = np.array([filt.update(s[t], f[t]) for t in range(len(s))][1:])
    np.testing.assert_allclose(online, batch(model, s, f)[5], atol=1e-12)


def test_scaled_passes_equal_the_pure_log_space_passes(rng):
    model = random_model(rng, 4, 3, 2)
    s, f = random_demo(rng, 3000, 3, 2)
    li, tr, lt, le = model._inference_arrays(s, f)
    N, K = le.shape
    g_fast, x_fast = np.empty((N, K)), np.empty((N, K, K))
    g_log, x_log = np.empty((N, K)), np.empty((N, K, K))
    ll_fast = inference.smoother_into(li, tr, lt, le, g_fast, x_fast)
    ll_log = inference.smoother_log_into(li, lt, le, g_log, x_log)
    assert ll_fast == pytest.approx(ll_log, rel=1e-12)
    np.testing.assert_allclose(g_fast, g_log, atol=1e-10)
    np.testing.assert_allclose(x_fast, x_log, atol=1e-10)
    alpha, log_c = inference.forward(li, tr, lt, le)
    la, log_c2 = inference.forward_log(li, lt, le)
    np.testing.assert_allclose(alpha, np.exp(la), atol=1e-12)
    np.testing.assert_allclose(log_c, log_c2, rtol=1e-12, atol=1e-9)
