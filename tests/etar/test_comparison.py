"""ETAR against STAR: the comparison's metrics on data whose answer is known."""

import numpy as np
import pytest

from etar import ETAR
from etar.comparison import (compare_transitions, evaluate, filtered_phases, match_by_parameters, near_transitions,
                             parameter_distances, separate_fits,
                             prediction_error_by_label, summarise)
from etar.metrics import score_demonstrations
from etar.synthetic import make_task, sample_demonstrations


@pytest.fixture(scope="module")
def task_data():
    task = make_task(3, seed=0)
    data = sample_demonstrations(task, 3, 300, seed=1)
    return task, [(s, f) for s, f, _ in data], [z for _, _, z in data]


def test_the_true_model_scores_near_perfectly_and_the_scores_are_the_metrics_of_its_segmentations(task_data):
    task, demos, truths = task_data
    e = evaluate(task.model, demos, truths, dt=0.01)
    assert e.viterbi.accuracy > 0.97 and e.filtered.accuracy > 0.95, (e.viterbi.accuracy, e.filtered.accuracy)
    v, _ = score_demonstrations(truths, [task.model.viterbi(s, f) for s, f in demos], 0.01, None, 3)
    assert e.viterbi.accuracy == v.accuracy and e.viterbi.spurious_switches == v.spurious_switches
    f, _ = score_demonstrations(truths, [filtered_phases(task.model, s, f) for s, f in demos], 0.01, None, 3)
    assert e.filtered.to_dict() == f.to_dict()
    assert np.isfinite(e.error_near_transitions) and np.isfinite(e.error_elsewhere)


def test_filtered_phases_are_the_filters_argmax_one_per_step(task_data):
    task, demos, _ = task_data
    s, f = demos[0]
    labels = filtered_phases(task.model, s, f)
    filt = task.model.filter()
    filt.update(s[0], f[0])
    expected = [int(np.argmax(filt.update(s[t], f[t]))) for t in range(1, len(s))]
    assert labels.tolist() == expected and labels.shape == (len(s) - 1,)


def test_prediction_error_and_the_transition_window_on_hand_made_arrays():
    model = ETAR(2)
    model.A = np.stack([np.eye(2), 2 * np.eye(2)])
    model.B = np.zeros((2, 2, 2))
    s = np.array([[1.0, 0.0], [1.0, 0.0], [3.0, 0.0], [3.0, 1.0]])
    f = np.zeros((4, 1))
    # phase 0 predicts s_t, phase 1 predicts 2 s_t
    err = prediction_error_by_label(model, s, f, [0, 1, 0])
    np.testing.assert_allclose(err, [0.0, (2 - 3) ** 2, 1.0])
    near = near_transitions([0, 0, 0, 1, 1, 1, 1, 1, 1, 1], steps=2)
    assert near.tolist() == [False, True, True, True, True, False, False, False, False, False]


def test_compare_fits_both_transition_models_per_seed_and_summarises(task_data):
    _, demos, truths = task_data
    evals = compare_transitions(demos[:2], truths[:2], 3, dt=0.01, seeds=(0, 1), max_iter=15, n_restarts=1)
    assert [(e.transitions, e.seed) for e in evals] == [("effect", 0), ("state", 0), ("effect", 1), ("state", 1)]
    summary = summarise(evals)
    assert set(summary) == {"ETAR", "STAR"} and summary["ETAR"]["seeds"] == [0, 1]
    acc = summary["ETAR"]["filter_accuracy"]
    assert acc["min"] <= acc["mean"] <= acc["max"]
    # the data come from an effect-driven process: ETAR fits them at least as well
    assert np.mean([e.log_likelihood for e in evals if e.transitions == "effect"]) >= \
        np.mean([e.log_likelihood for e in evals if e.transitions == "state"]) - 1.0


def permuted_copy(model, p):
    """``model`` with its phase p[k] as phase k."""
    import copy

    m = copy.deepcopy(model)
    p = np.asarray(p)
    m.A, m.B, m.Sigma = np.asarray(model.A)[p], np.asarray(model.B)[p], np.asarray(model.Sigma)[p]
    W = np.asarray(model.W)
    m.W = np.concatenate([W[:1], W[1:][p]], axis=0)[:, p]
    return m


def test_table_c1_matching_undoes_a_permutation_and_the_softmax_gauge(task_data):
    task, _, _ = task_data
    model = task.model
    p = [2, 0, 1]
    other = permuted_copy(model, p)
    d = parameter_distances(model, other)
    assert d["permutation"] == np.argsort(p).tolist()
    assert all(d[k] < 1e-12 for k in ("A", "B", "Sigma", "W")), d
    # the same vector added to every destination's weights changes no probability: no distance
    shifted = permuted_copy(model, [0, 1, 2])
    shifted.W = np.asarray(model.W) + np.random.default_rng(0).normal(size=(model.W.shape[0], 1, model.W.shape[2]))
    assert parameter_distances(model, shifted)["W"] < 1e-12
    # a real change of one phase's dynamics is measured, relative to the parameter's size
    changed = permuted_copy(model, [0, 1, 2])
    changed.A = np.asarray(model.A).copy()
    changed.A[1] *= 1.1
    dist = parameter_distances(model, changed)
    expected = np.linalg.norm(0.1 * model.A[1]) / (0.5 * (np.linalg.norm(model.A) + np.linalg.norm(changed.A)))
    assert dist["A"] == pytest.approx(expected) and dist["B"] == 0.0
    with pytest.raises(ValueError, match="3 and 2 phases"):
        match_by_parameters(model, ETAR(2))


def test_table_c1_separate_fits_of_two_demonstrations_of_one_task(task_data):
    task, demos, truths = task_data
    c1 = separate_fits(demos[0], demos[1], 3, seeds=(0, 1), truths=truths[:2], max_iter=15, n_restarts=1)
    assert [r["seed"] for r in c1["between_demonstrations"]] == [0, 1]
    assert [(r["demonstration"], r["seeds"]) for r in c1["between_seeds"]] == [("a", [0, 1]), ("b", [0, 1])]
    for row in c1["between_demonstrations"]:
        assert sorted(row["permutation"]) == [0, 1, 2]
        # the synthetic phases differ clearly: matching by the dynamics finds the truth's matching
        assert row["matching_agrees_with_truth"], row
        assert 0.0 <= row["A"] < 0.5 and np.isfinite(row["Sigma"]) and np.isfinite(row["W"])
    s = c1["summary"]["A"]["between_demonstrations"]
    assert s["min"] <= s["mean"] <= s["max"]
    assert set(c1["models"]) == {"a_seed0", "a_seed1", "b_seed0", "b_seed1"}
