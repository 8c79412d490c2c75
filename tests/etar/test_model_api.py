"""The model's public surface: assigned parameters, file format, bad input."""

import json

import numpy as np
import pytest

from etar import ETAR, DemonstrationError
from etar.synthetic import make_task, sample_demonstrations


@pytest.fixture(scope="module")
def task_and_demos():
    task = make_task(3, seed=0)
    data = sample_demonstrations(task, 3, 300, seed=1)
    return task, [(s, f) for s, f, _ in data]


def test_assigned_parameters_work_without_fit(task_and_demos):
    task, demos = task_and_demos
    model = ETAR(3)
    model.A, model.B, model.Sigma, model.W = (getattr(task.model, k).copy() for k in ("A", "B", "Sigma", "W"))
    s, f = demos[0]
    assert np.isfinite(model.log_likelihood(demos))
    assert model.posterior(s, f).shape == (len(s) - 1, 3)
    assert model.viterbi(s, f).dtype.kind == "i"
    assert model.filter().update(s[0], f[0]).shape == (3,)


def test_no_parameters_is_a_clear_error(task_and_demos):
    _, demos = task_and_demos
    with pytest.raises(RuntimeError, match="no parameters"):
        ETAR(2).log_likelihood(demos)


def test_wrongly_shaped_assigned_parameters_are_named(task_and_demos):
    task, demos = task_and_demos
    model = ETAR(3)
    model.A, model.B, model.Sigma = task.model.A, task.model.B, task.model.Sigma
    model.W = np.zeros((3, 3, 4))
    with pytest.raises(ValueError, match=r"W must have shape \(K\+1=4"):
        model.posterior(*demos[0])
    model.W = task.model.W
    model.Sigma = -task.model.Sigma
    with pytest.raises(ValueError, match=r"Sigma\[0\] is not symmetric positive definite"):
        model.posterior(*demos[0])


def test_save_load_round_trip_is_exact(tmp_path, task_and_demos):
    _, demos = task_and_demos
    model = ETAR(3).fit(demos, max_iter=20)
    model.metadata["note"] = "round trip"
    path = tmp_path / "model.json"
    model.save(path)
    data = json.loads(path.read_text())  # human-readable JSON
    assert data["format"] == "etar-model" and data["version"] == 1
    assert np.array(data["parameters"]["W"]).shape == (4, 3, 4)
    loaded = ETAR.load(path)
    for name in ("A", "B", "Sigma", "W"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(model, name))
    assert loaded.metadata["note"] == "round trip"
    assert loaded.log_likelihood(demos) == model.log_likelihood(demos)


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda d: d.pop("parameters"), "field 'parameters' is missing"),
        (lambda d: d["parameters"].pop("Sigma"), r"field 'parameters.Sigma' is missing"),
        (lambda d: d.update(format="other"), "field 'format'"),
        (lambda d: d.update(version=99), "field 'version'"),
        (lambda d: d["parameters"].update(A="abc"), r"parameters.A"),
        (lambda d: d["parameters"].update(W=[[0.0]]), "W must have shape"),
        # JSON's integers have no bound: one past float64's range, in the arrays and in a
        # hyperparameter (both raised OverflowError; a bad hyperparameter's message lacked the file)
        (lambda d: d["parameters"]["A"][0][0].__setitem__(0, 10**400), r"parameters.A' is not a numeric array"),
        (lambda d: d["hyperparameters"].update(w_l2=10**400), "w_l2 must be a finite number >= 0"),
        (lambda d: d["hyperparameters"].update(ab_prior=-1.0), "ab_prior must be a finite number >= 0"),
        # both raised TypeError, with no file named
        (lambda d: d.update(metadata=[1]), r"field 'metadata' must be a JSON object, got \[1\]"),
        (lambda d: d["parameters"].update(goal={}), r"field 'parameters.goal' is not a numeric array"),
    ],
)
def test_corrupt_model_file_names_file_and_field(tmp_path, task_and_demos, mutate, match):
    task, _ = task_and_demos
    data = task.model.to_dict()
    mutate(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=match) as info:
        ETAR.load(path)
    assert str(path) in str(info.value)


def test_not_json_is_a_clear_error(tmp_path):
    path = tmp_path / "model.json"
    path.write_text("{ truncated")
    with pytest.raises(ValueError, match="not a JSON model file"):
        ETAR.load(path)


def test_bad_demonstrations_are_clear_errors(task_and_demos):
    _, demos = task_and_demos
    s, f = demos[0]
    model = ETAR(2)
    with pytest.raises(DemonstrationError, match=r"demonstration 1: forces has 299 samples|states has 300 samples but forces has 299"):
        model.fit([demos[0], (s, f[:-1])])
    bad = f.copy()
    bad[17, 2] = np.nan
    with pytest.raises(DemonstrationError, match=r"demonstration 0: forces\[17, 2\] is nan"):
        model.fit([(s, bad)])
    with pytest.raises(DemonstrationError, match="must be 2-D"):
        model.fit([(s[:, 0], f)])
    with pytest.raises(DemonstrationError, match="states has 2 columns, expected 3"):
        model.fit([demos[0], (s[:, :2], f)])
    with pytest.raises(DemonstrationError, match="single"):
        model.fit((s, f))
    with pytest.raises(DemonstrationError, match="no demonstrations"):
        model.fit([])
    with pytest.raises(DemonstrationError, match="at least 2 samples"):
        model.fit([(s[:1], f[:1])])
    with pytest.raises(DemonstrationError, match="fewer than the .* free parameters"):
        ETAR(3).fit([(s[:40], f[:40])])
    with pytest.raises(DemonstrationError, match="expected a \\(states, forces\\) pair"):
        model.fit([s])


def test_bad_hyperparameters_are_clear_errors():
    with pytest.raises(ValueError, match="n_phases"):
        ETAR(0)
    with pytest.raises(ValueError, match="transitions"):
        ETAR(2, transitions="force")
    with pytest.raises(ValueError, match="solver"):
        ETAR(2, solver="adam")
    with pytest.raises(ValueError, match="w_l2"):
        ETAR(2, w_l2=float("nan"))


def test_inference_checks_dimensions_against_the_model(task_and_demos):
    task, demos = task_and_demos
    s, f = demos[0]
    with pytest.raises(DemonstrationError, match="forces has 2 columns, expected 3"):
        task.model.posterior(s, f[:, :2])


def test_a_filter_joining_a_task_under_way_starts_uniform_and_finds_the_phase(task_and_demos):
    """A restarted estimator's filter: started in the middle of a demonstration, the
    'uniform' start gives every phase the same weight at the first sample, then follows
    the samples; it agrees with the true phase at least as often as the learned
    initial-phase prior (which assumes the task begins there) over the next 50 samples."""
    task, demos = task_and_demos
    data = sample_demonstrations(task, 3, 300, seed=1)
    hits = {"first": 0, "uniform": 0}
    for s, f, truth in data:
        later = np.flatnonzero(truth > 0)
        t0 = int(later[0]) + 5 if later.size else len(s) // 2  # under way: past the first phase
        for start in hits:
            filt = task.model.filter(start=start)
            first = filt.update(s[t0], f[t0])
            if start == "uniform":
                np.testing.assert_allclose(first, 1.0 / 3)
            for t in range(t0 + 1, min(t0 + 51, len(s))):
                hits[start] += int(np.argmax(filt.update(s[t], f[t])) == truth[t - 1])
    assert hits["uniform"] >= hits["first"] and hits["uniform"] > 0.8 * 150, hits
    with pytest.raises(ValueError, match="start must be"):
        task.model.filter(start="middle")


def test_a_fit_can_start_from_a_given_segmentation():
    """``start_labels`` (e.g. the true phases of simulated demonstrations): one EM run from
    that segmentation instead of the restarts.  From the true phases it keeps them (the
    phases' numbers too); labels that do not fit the demonstrations are named."""
    from etar.metrics import score_segmentation

    task = make_task(3, seed=0)
    data = sample_demonstrations(task, 3, 300, seed=1)
    demos = [(s, f) for s, f, _ in data]
    truth = [z for _, _, z in data]  # the phase of every step
    model = ETAR(3, n_restarts=4).fit(demos, max_iter=40, start_labels=truth)
    assert model.fit_report_.restart_objectives and len(model.fit_report_.restart_objectives) == 1
    for (s, f), z in zip(demos, truth):
        path = model.viterbi(s, f)
        assert score_segmentation(z, path, mapping={0: 0, 1: 1, 2: 2}).accuracy > 0.95
    wrong = [np.zeros(len(z), dtype=np.int64) for z in truth]
    wrong[0][-5:] = 1
    wrong[1][-5:] = 2
    other = ETAR(3).fit(demos, max_iter=40, start_labels=wrong)
    assert other.log_likelihood(demos) != model.log_likelihood(demos)
    with pytest.raises(ValueError, match=r"start_labels\[1\]: expected 299 integer phases"):
        ETAR(3).fit(demos, start_labels=[truth[0], truth[1][:-1], truth[2]])
    with pytest.raises(ValueError, match=r"start_labels\[2\]: phases must be 0..2, got 0..3"):
        ETAR(3).fit(demos, start_labels=[truth[0], truth[1], truth[2] + (truth[2] == 2)])
    with pytest.raises(ValueError, match="2 label sequences for 3 demonstrations"):
        ETAR(3).fit(demos, start_labels=truth[:2])
    with pytest.raises(ValueError, match=r"phase\(s\) \[3\] label no step"):
        ETAR(4).fit(demos, start_labels=truth)
