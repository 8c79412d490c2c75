"""EM: monotone objective, parameter recovery, BIC order selection, robustness."""

import warnings

import numpy as np
import pytest

from etar import ETAR, em
from etar.demonstrations import step_arrays
from etar.metrics import score_demonstrations
from etar.selection import select_order, vote_order
from etar.synthetic import make_task, sample_demonstrations


def synthetic(n_phases=3, task_seed=0, n_demos=6, length=600, seed=1):
    task = make_task(n_phases, seed=task_seed)
    data = sample_demonstrations(task, n_demos, length, seed=seed)
    return task, [(s, f) for s, f, _ in data], [p for *_, p in data]


def test_em_objective_never_decreases():
    _, demos, _ = synthetic(3, n_demos=3, length=400)
    model = ETAR(3, n_restarts=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the monitor warns on any decrease
        model.fit(demos, max_iter=60, tol=0)
    h = np.array(model.fit_report_.history)
    assert len(h) == 61
    assert np.all(np.diff(h) >= -1e-9 * np.abs(h[1:])), np.diff(h).min()
    assert h[-1] > h[0] + 1.0


def test_maximum_likelihood_em_log_likelihood_never_decreases():
    """With every prior switched off the tracked objective is the log-likelihood itself."""
    _, demos, _ = synthetic(2, n_demos=3, length=400)
    model = ETAR(2, n_restarts=1, sigma_prior_weight=0.0, ab_prior=0.0, w_l2=0.0)
    model.fit(demos, max_iter=40, tol=0)
    h = np.array(model.fit_report_.history)
    assert np.all(np.diff(h) >= -1e-9 * np.abs(h[1:]))
    assert model.fit_report_.log_likelihood == pytest.approx(h[-1], rel=1e-12)
    assert model.log_likelihood(demos) == pytest.approx(h[-1], rel=1e-12)


def test_parameters_recovered_from_data_generated_by_known_parameters():
    task, demos, truth = synthetic(3, task_seed=0, n_demos=6, length=600, seed=1)
    model = ETAR(3).fit(demos, seed=0)
    paths = [model.viterbi(s, f) for s, f in demos]
    overall, _ = score_demonstrations(truth, paths, n_pred=3)
    assert overall.accuracy > 0.995
    assert overall.spurious_switches == 0
    true = task.model
    X_all = np.vstack([np.hstack([s[:-1], f[:-1], np.ones((len(s) - 1, 1))]) for s, f in demos])
    labels = np.concatenate(truth)
    for k_est, k_true in overall.mapping.items():
        # one-step predictions on the phase's own steps agree to a fraction of the noise (1e-4 m)
        X = X_all[labels == k_true]
        C_est = np.concatenate([model.A[k_est], model.B[k_est]], axis=1)
        C_true = np.concatenate([true.A[k_true], true.B[k_true]], axis=1)
        diff = X @ (C_est - C_true).T
        assert np.sqrt(np.mean(diff**2)) < 2e-5
        # force-to-motion map (how contact absorbs force) within 5 %
        np.testing.assert_allclose(model.B[k_est][:, :3], true.B[k_true][:, :3], atol=5e-5)
        np.testing.assert_allclose(np.diag(model.Sigma[k_est]), np.diag(true.Sigma[k_true]), rtol=0.1)
    # the learned model explains the data at least as well as the truth
    assert model.log_likelihood(demos) >= true.log_likelihood(demos) - 1.0


@pytest.mark.parametrize("n_phases,task_seed", [(3, 0), (3, 1), (3, 2), (2, 3), (4, 4)])
def test_bic_picks_the_true_number_of_phases(n_phases, task_seed):
    _, demos, _ = synthetic(n_phases, task_seed=task_seed, n_demos=4, length=400, seed=task_seed + 10)
    sel = select_order(demos, range(1, 6), "bic", seed=0, n_restarts=2)
    assert sel.best == n_phases, sel.table()
    assert set(sel.scores) == {1, 2, 3, 4, 5}
    assert sel.model.n_phases == n_phases
    # the count used is this model's, not a Gaussian HMM's
    assert sel.n_parameters[3] == ETAR.count_free_parameters(3, 3, 3) == 3 * (9 + 12 + 6) + 4 * 2 * 4


@pytest.mark.slow
def test_per_demonstration_vote_picks_the_true_number_of_phases():
    _, demos, _ = synthetic(3, task_seed=0, n_demos=3, length=500, seed=10)
    messages = []
    vote = vote_order(demos, range(1, 6), "bic", seed=0, n_restarts=2, progress=messages.append)
    assert vote.best == 3, vote.table()
    assert vote.votes.get(3, 0) >= 2 and sum(vote.votes.values()) == 3
    assert len(vote.per_demonstration) == 3 and len(messages) == 3
    # each demonstration was scored on its own steps only
    assert [sel.n_samples for sel in vote.per_demonstration] == [len(s) - 1 for s, _ in demos]
    d = vote.to_dict()
    assert d["method"] == "per_demonstration" and d["best"] == 3
    assert set(d["per_demonstration"][0]["scores"]) == {"1", "2", "3", "4", "5"}
    assert "votes {" in vote.table() and vote.table().count("\n") == 4


def test_per_demonstration_tie_goes_to_fewer_phases():
    # one demonstration of a 2-phase task and one of a 3-phase task: one vote each
    _, two, _ = synthetic(2, task_seed=3, n_demos=1, length=500, seed=13)
    _, three, _ = synthetic(3, task_seed=0, n_demos=1, length=500, seed=10)
    vote = vote_order(two + three, range(1, 5), "bic", seed=0, n_restarts=2)
    assert [sel.best for sel in vote.per_demonstration] == [2, 3], vote.table()
    assert vote.best == 2


def test_aic_is_available_and_penalises_less():
    _, demos, _ = synthetic(2, task_seed=3, n_demos=3, length=300)
    bic = select_order(demos, [1, 2, 3], "bic", n_restarts=1)
    aic = select_order(demos, [1, 2, 3], "aic", n_restarts=1)
    for k in (1, 2, 3):
        assert aic.log_likelihoods[k] == pytest.approx(bic.log_likelihoods[k])
        assert aic.scores[k] < bic.scores[k]
    with pytest.raises(ValueError, match="criterion"):
        select_order(demos, [1, 2], "dic")


def test_ragged_demonstrations():
    task = make_task(3, seed=0)
    data = sample_demonstrations(task, 4, (150, 700), seed=3)
    demos = [(s, f) for s, f, _ in data]
    lengths = {len(s) for s, _ in demos}
    assert len(lengths) == 4
    model = ETAR(3).fit(demos, seed=0)
    total = sum(model.log_likelihood([d]) for d in demos)
    assert model.log_likelihood(demos) == pytest.approx(total, rel=1e-12)
    for s, f in demos:
        assert model.posterior(s, f).shape == (len(s) - 1, 3)
        assert model.viterbi(s, f).shape == (len(s) - 1,)
    overall, _ = score_demonstrations([p for *_, p in data], [model.viterbi(s, f) for s, f in demos], n_pred=3)
    assert overall.accuracy > 0.99


def test_same_seed_same_result_and_different_seed_changes_restarts():
    _, demos, _ = synthetic(3, n_demos=3, length=300)
    a = ETAR(3).fit(demos, seed=5, max_iter=30)
    b = ETAR(3).fit(demos, seed=5, max_iter=30)
    for name in ("A", "B", "Sigma", "W"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    c = ETAR(3).fit(demos, seed=6, max_iter=30)
    assert a.fit_report_.restart_objectives[1:] != c.fit_report_.restart_objectives[1:]


def test_phase_without_data_stays_finite():
    # two phases worth of data, four phases in the model
    _, demos, _ = synthetic(2, task_seed=3, n_demos=3, length=400)
    model = ETAR(5).fit(demos, seed=0, max_iter=50)
    for name in ("A", "B", "Sigma", "W"):
        assert np.all(np.isfinite(getattr(model, name))), name
    assert np.all(np.linalg.eigvalsh(model.Sigma) > 0)
    assert np.isfinite(model.log_likelihood(demos))


def test_m_step_of_an_empty_phase_returns_the_prior():
    _, demos, _ = synthetic(2, task_seed=3, n_demos=2, length=200)
    stacked = em.StackedSteps.from_steps([step_arrays(s, f, "effect") for s, f in demos])
    gamma = np.zeros((stacked.n_samples, 2))
    gamma[:, 0] = 1.0  # phase 1 gets nothing
    priors = em.Priors(1.0, 1e-8 * np.eye(3), 1e-6, 1e-3)
    C, Sigma = em.m_step_dynamics(stacked, gamma, priors)
    p = C.shape[2]
    np.testing.assert_allclose(C[1][:, :3], np.eye(3), atol=1e-12)  # stays where it is
    np.testing.assert_allclose(C[1][:, 3:], 0.0, atol=1e-12)
    np.testing.assert_allclose(Sigma[1], 1e-8 * np.eye(3) / (1.0 + p), rtol=1e-9)
    assert np.all(np.isfinite(C)) and np.all(np.linalg.eigvalsh(Sigma) > 0)


def test_noise_free_phase_does_not_collapse():
    """A phase that the dynamics explain exactly must keep a positive covariance."""
    rng = np.random.default_rng(0)
    T = 300
    forces = rng.normal(size=(T, 1))
    states = np.zeros((T, 1))
    for t in range(T - 1):
        states[t + 1] = states[t] + 1e-3 * forces[t]  # exactly linear: zero residual
    model = ETAR(2, n_restarts=1).fit([(states, forces)], max_iter=20)
    assert np.all(np.linalg.eigvalsh(model.Sigma) > 0)
    assert np.isfinite(model.log_likelihood([(states, forces)]))


def test_softmax_m_step_descends_and_lbfgs_reaches_at_least_the_same_objective():
    _, demos, _ = synthetic(3, n_demos=3, length=400)
    model = ETAR(3).fit(demos, max_iter=20)
    stacked = em.StackedSteps.from_steps([step_arrays(s, f, "effect") for s, f in demos])
    C = np.concatenate([model.A, model.B], axis=2)
    ex = em.e_step(stacked, C, model.Sigma, model.W)
    from etar.softmax_regression import softmax_regression_objective

    w0 = np.zeros_like(model.W[1:])
    f0, _ = softmax_regression_objective(w0, stacked.features, ex.xi, 1e-3)
    gd = em.fit_softmax_blocks(w0, stacked.features, ex.xi, 1e-3, "gd", max_steps=200)
    lb = em.fit_softmax_blocks(w0, stacked.features, ex.xi, 1e-3, "lbfgs", max_steps=200)
    f_gd, _ = softmax_regression_objective(gd, stacked.features, ex.xi, 1e-3)
    f_lb, _ = softmax_regression_objective(lb, stacked.features, ex.xi, 1e-3)
    assert np.all(f_gd < f0) and np.all(f_lb < f0)
    # the quasi-Newton option must reach at least the objective of gradient descent
    assert np.all(f_lb <= f_gd * (1 + 1e-9))
    lbfgs_model = ETAR(3, solver="lbfgs").fit(demos, max_iter=20)
    assert np.isfinite(lbfgs_model.fit_report_.objective)


def test_star_fits_with_state_features():
    task, demos, truth = synthetic(3, n_demos=4, length=400)
    model = ETAR(3, transitions="state").fit(demos, seed=0)
    assert model.W.shape == (4, 3, 4)
    np.testing.assert_allclose(model.goal, np.mean([s[-1] for s, _ in demos], axis=0))
    assert np.isfinite(model.log_likelihood(demos))
    assert model.n_free_parameters == ETAR.count_free_parameters(3, 3, 3, 3)


@pytest.mark.skipif(not __import__("kernel_plumbing.blas").blas.AVAILABLE, reason="numpy's BLAS not callable here")
def test_compiled_softmax_descent_gives_the_numpy_paths_bits(monkeypatch):
    """The W step's descent compiled (etar.softmax_regression.preconditioned_steps) stands in
    for the numpy path only because it gives the same bits: over a long descent and whole fits."""
    assert em._compiled("steps") and em._compiled("factors")
    _, demos, _ = synthetic(3, n_demos=2, length=300)
    stacked = em.StackedSteps.from_steps([step_arrays(s, f, "effect") for s, f in demos])
    model = ETAR(3).fit(demos, max_iter=5)
    ex = em.e_step(stacked, np.concatenate([model.A, model.B], axis=2), model.Sigma, model.W)
    import numba

    got = {}
    threads = numba.get_num_threads()
    numba.set_num_threads(1)  # where the descent is compiled: a pool's fits
    try:
        for compiled in (True, False):
            monkeypatch.setattr(em, "_CHECKED", {"steps": compiled, "factors": compiled})
            descent = em.fit_softmax_blocks(np.zeros_like(model.W[1:]), stacked.features, ex.xi, 1e-3, max_steps=200)
            fit = ETAR(4).fit(demos, max_iter=40, seed=3)
            got[compiled] = descent, fit.fit_report_.history, fit.W, fit.A, fit.Sigma
    finally:
        numba.set_num_threads(threads)
    for a, b in zip(got[True], got[False]):
        assert np.array_equal(a, b)
    assert not np.array_equal(got[True][0], np.zeros_like(model.W[1:]))  # it did descend


def test_compiled_softmax_descent_says_when_a_solve_fails():
    from etar.softmax_regression import preconditioned_steps, softmax_regression_objective
    from kernel_plumbing import blas

    if not blas.AVAILABLE:
        pytest.skip("numpy's BLAS not callable here")
    rng = np.random.default_rng(0)
    features = np.hstack([rng.standard_normal((50, 3)), np.ones((50, 1))])
    targets = rng.dirichlet(np.ones(3), size=(50, 2))
    w = np.zeros((2, 3, 4))
    value, grad = softmax_regression_objective(w, features, targets, 1e-3)
    singular = np.zeros((2, 12, 12))  # numpy's solve raises LinAlgError: the caller takes that path
    assert preconditioned_steps(w, features, targets, 1e-3, singular, value, grad, 3, blas.GESV, blas.DOT) > 0
    assert not w.any()


@pytest.mark.skipif(not __import__("kernel_plumbing.blas").blas.AVAILABLE, reason="numpy's BLAS not callable here")
def test_a_ctrl_c_during_the_compiled_descents_check_is_not_swallowed(monkeypatch):
    """The first W step checks the compiled descent against numpy; a Ctrl-C landing in that
    check (numba raises it as a SystemError caused by the KeyboardInterrupt) must interrupt,
    not count as 'the kernel failed' and let the fit run on."""
    def interrupted(*args):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise SystemError("<numba dispatcher> returned a result with an exception set") from exc

    monkeypatch.setattr(em, "_CHECKED", {})
    monkeypatch.setattr(em, "preconditioned_steps", interrupted)
    with pytest.raises(KeyboardInterrupt):
        em._compiled("steps")
    assert em._CHECKED == {}  # asked again next time
