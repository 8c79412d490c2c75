"""The learned task: made once from a fit, saved in the model file, and refused with an
error naming the file, the field and the value whenever it could not be reproduced."""

import json

import numpy as np
import pytest

from etar import ETAR
from etar.synthetic import make_task, sample_demonstrations
from etar.task import LearnedTask, TaskError, learn_task, load_task


@pytest.fixture(scope="module")
def learned(tmp_path_factory):
    truth = make_task(3, seed=0)
    data = sample_demonstrations(truth, 2, 300, seed=1)
    demos = [dict(states=s, forces=f, phases=p) for s, f, p in data]
    model = ETAR(3, n_restarts=1).fit([(d["states"], d["forces"]) for d in demos], max_iter=30, seed=0)
    task = learn_task(model, demos, 0.01, sources=["a.npz", "b.npz"])
    path = task.save(tmp_path_factory.mktemp("task") / "sub" / "model.json")
    return task, path, demos


def edited(path, tmp_path, change):
    data = json.loads(path.read_text())
    change(data)
    out = tmp_path / "edited.json"
    out.write_text(json.dumps(data))
    return out


def test_a_task_is_made_from_a_fit_and_reads_back_the_same(learned):
    task, path, demos = learned
    assert task.state == "position" and task.features == "force" and task.dt == 0.01
    np.testing.assert_allclose(task.goal, np.mean([d["states"][-1] for d in demos], axis=0))
    assert sorted(task.phase_to_truth) == [0, 1, 2] and sorted(task.phase_to_truth.values()) == [0, 1, 2]
    back = load_task(path)
    assert back.source == str(path)
    np.testing.assert_array_equal(back.goal, task.goal)
    assert back.phase_to_truth == task.phase_to_truth and back.demonstrations == ("a.npz", "b.npz")
    for a, b in zip(back.impedances, task.impedances):
        np.testing.assert_array_equal(a.stiffness, b.stiffness)
    np.testing.assert_array_equal(back.model.Sigma, task.model.Sigma)


@pytest.mark.parametrize("change, field, words", [
    (lambda d: d["metadata"].pop("goal"), "metadata.goal", "missing"),
    (lambda d: d["metadata"].pop("impedance"), "metadata.impedance", "missing"),
    (lambda d: d["metadata"].update(goal=[0.1, float("nan"), 0.2]), "metadata.goal", "3 finite numbers"),
    (lambda d: d["metadata"]["impedance"].pop(), "metadata.impedance", "one entry per phase (3)"),
    (lambda d: d["metadata"]["impedance"][1]["stiffness"][0].__setitem__(0, float("nan")),
     "metadata.impedance[1].stiffness", "finite"),
    (lambda d: d["metadata"]["impedance"][0]["mean_force"].__setitem__(2, float("inf")),
     "metadata.impedance[0].mean_force", "finite"),
    (lambda d: d["metadata"].update(dt=0), "metadata.dt", "> 0"),
    (lambda d: d["metadata"].update(state="pose"), "metadata.state", "3 columns"),
    (lambda d: d["metadata"].update(phase_to_truth={"7": 0}), "metadata.phase_to_truth", "0..2"),
    (lambda d: d["metadata"].update(state_resolution=-0.001), "metadata.state_resolution", "pitch >= 0 m"),
    (lambda d: d["metadata"].update(state_resolution="1 mm"), "metadata.state_resolution", "pitch >= 0 m"),
    (lambda d: d.update(n_state=6), "model", "'n_state' is 6, but the parameters have 3"),
    (lambda d: d["parameters"]["Sigma"].__setitem__(2, (-np.array(d["parameters"]["Sigma"][2])).tolist()), "model",
     "'parameters.Sigma[2]' is not positive definite"),
])
def test_a_task_that_cannot_be_reproduced_is_refused_naming_file_field_and_value(learned, tmp_path, change, field,
                                                                                  words):
    _, path, _ = learned
    bad = edited(path, tmp_path, change)
    with pytest.raises(TaskError) as err:
        load_task(bad)
    text = str(err.value)
    assert text.startswith(f"{bad}: {field}"), text
    assert words in text, text


def test_files_that_are_no_model_are_refused_in_one_line(tmp_path):
    listed = tmp_path / "list.json"
    listed.write_text("[1, 2, 3]")
    with pytest.raises(TaskError, match=r"list\.json: model: expected a JSON object"):
        load_task(listed)
    with pytest.raises(TaskError, match="no such model file"):
        load_task(tmp_path / "missing.json")
    broken = tmp_path / "broken.json"
    broken.write_text('{"format": ')
    with pytest.raises(TaskError, match="not a JSON model file"):
        load_task(broken)


def test_a_task_is_checked_when_it_is_made_too(learned):
    task, _, _ = learned
    with pytest.raises(TaskError, match="metadata.features"):
        LearnedTask(model=task.model, impedances=task.impedances, goal=task.goal, dt=0.01, features="force_torque")
    with pytest.raises(TaskError, match="nothing to reproduce"):
        LearnedTask(model=task.model, impedances=(None, None, None), goal=task.goal, dt=0.01)


def test_a_coarser_state_is_kept_with_the_task_and_rounds_only_the_position():
    from etar.features import state_vector

    # a tool turned 0.3 rad about z, at a position between grid points
    c, s = np.cos(0.3), np.sin(0.3)
    cart = [c, -s, 0, 0.6213, s, c, 0, -0.0987, 0, 0, 1, 0.3004]
    np.testing.assert_allclose(state_vector(cart, "position", resolution=0.002), [0.622, -0.098, 0.300])
    np.testing.assert_array_equal(state_vector(cart, "position"), [0.6213, -0.0987, 0.3004])
    pose = state_vector(cart, "pose", np.eye(3), resolution=0.002)
    np.testing.assert_allclose(pose, [0.622, -0.098, 0.300, 0, 0, 0.3])


def test_a_tasks_state_resolution_reads_back_and_is_absent_from_files_without_one(learned, tmp_path):
    task, path, _ = learned
    assert task.state_resolution == 0.0 and "state_resolution" not in json.loads(path.read_text())["metadata"]
    # a copy of the model: saving writes the task into its model's metadata
    coarse = LearnedTask(model=ETAR.from_dict(task.model.to_dict()), impedances=task.impedances, goal=task.goal, dt=0.01,
                         state_resolution=0.001)
    assert load_task(coarse.save(tmp_path / "coarse.json")).state_resolution == 0.001
