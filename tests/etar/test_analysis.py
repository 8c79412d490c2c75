"""Prediction-error table, impedance derivation, segmentation metrics."""

import numpy as np
import pytest

from etar.analysis import prediction_errors
from etar.impedance import derive_impedance, phase_impedances
from etar.metrics import match_phases, score_demonstrations, score_segmentation
from etar.synthetic import make_task, sample_demonstrations


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


# ---------------------------------------------------------------- prediction errors


def test_each_phase_is_predicted_best_by_its_own_parameters():
    task = make_task(3, seed=0)
    data = sample_demonstrations(task, 3, 400, seed=1)
    demos = [(s, f) for s, f, _ in data]
    table = prediction_errors(task.model, demos, labels=[p for *_, p in data])
    assert table.mse.shape == (3, 3)
    assert table.diagonal_is_best.all(), table.table()
    # on its own phase the error is the noise: n * sigma^2 = 3e-8
    np.testing.assert_allclose(np.diag(table.mse), 3e-8, rtol=0.2)
    assert table.count.sum() == sum(len(p) for *_, p in data)
    assert "theta_0" in table.table()


def test_prediction_errors_default_to_viterbi_and_check_labels():
    task = make_task(2, seed=3)
    data = sample_demonstrations(task, 2, 200, seed=1)
    demos = [(s, f) for s, f, _ in data]
    table = prediction_errors(task.model, demos)
    assert table.diagonal_is_best.all()
    with pytest.raises(ValueError, match="labels\\[0\\] must have shape"):
        prediction_errors(task.model, demos, labels=[np.zeros(3, int), np.zeros(3, int)])
    with pytest.raises(ValueError, match="outside"):
        prediction_errors(task.model, demos, labels=[np.full(len(p), 5) for *_, p in data])


# ---------------------------------------------------------------- impedance


def test_free_motion_has_no_compliant_axis():
    rng = np.random.default_rng(0)
    d = unit([1, 2, -0.5])
    v = 0.05 * d + 0.002 * rng.normal(size=(200, 3))
    f = 0.3 * rng.normal(size=(200, 3))  # sensor noise only
    imp = derive_impedance(v, f)
    assert imp.n_compliant == 0
    assert imp.direction @ d > 0.999
    np.testing.assert_allclose(imp.stiffness, 2000.0 * np.eye(3), atol=1e-9)


def test_free_motion_ending_in_a_few_touches_stays_free():
    # the segmentation gives the free-motion phase the first samples of the contact
    # that follows: 10 of 200 samples touch a plate with 9 N.  Taken as contact they
    # made a compliant axis and a 5 N feedforward push in free space (the arm drifted
    # off the plate in a reproduction).
    rng = np.random.default_rng(3)
    d = unit([0.0, 0.0, -1.0])
    v = 0.05 * d + 0.002 * rng.normal(size=(200, 3))
    f = 0.3 * rng.normal(size=(200, 3))
    f[-10:] += [0.0, 4.7, 8.1]
    imp = derive_impedance(v, f)
    assert imp.n_compliant == 0 and imp.n_contact_samples == 0
    np.testing.assert_array_equal(imp.mean_force, np.zeros(3))
    # the same touches over most of the phase do make it a contact phase
    f[:150] += [0.0, 4.7, 8.1]
    assert derive_impedance(v, f).n_compliant >= 1


def test_sliding_on_a_plate_has_one_compliant_axis_along_its_normal():
    rng = np.random.default_rng(1)
    normal = unit([0, 1, 1])  # a 45 degree plate, as in the valley
    along = unit(np.cross(normal, [1, 0, 0]))
    v = 0.04 * along + 0.001 * rng.normal(size=(300, 3))
    f = 12.0 * normal - 3.0 * along + 0.5 * rng.normal(size=(300, 3))  # reaction + friction
    imp = derive_impedance(v, f)
    assert imp.n_compliant == 1
    assert abs(imp.compliant_axes[0] @ normal) > 0.99
    assert imp.direction @ along > 0.99
    K = imp.stiffness
    np.testing.assert_allclose(K, K.T)
    assert normal @ K @ normal == pytest.approx(100.0, rel=0.05)
    assert imp.direction @ K @ imp.direction == pytest.approx(2000.0)
    np.testing.assert_allclose(imp.rotation.T @ imp.rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(imp.rotation) == pytest.approx(1.0)


def test_sliding_along_a_groove_has_two_compliant_axes_and_finds_the_groove():
    rng = np.random.default_rng(2)
    groove = unit([-1, 0, 0])
    n1, n2 = unit([0, 1, 1]), unit([0, -1, 1])
    v = 0.03 * groove + 0.001 * rng.normal(size=(400, 3))
    a = rng.uniform(3, 15, size=(400, 1))
    b = rng.uniform(3, 15, size=(400, 1))
    f = a * n1 + b * n2 + 0.3 * rng.normal(size=(400, 3))
    imp = derive_impedance(v, f)
    assert imp.n_compliant == 2
    assert imp.direction @ groove > 0.995
    # the compliant plane is the one orthogonal to the groove
    assert np.abs(imp.compliant_axes @ groove).max() < 0.1
    assert groove @ imp.stiffness @ groove == pytest.approx(2000.0, rel=0.01)


def test_direction_is_recovered_from_deflected_motion():
    """The robot aims at d; contact with varying normals deflects v within span(d, f)."""
    rng = np.random.default_rng(3)
    d = unit([1, 0, -1])
    vs, fs = [], []
    for _ in range(300):
        n = unit(rng.normal(size=3) + [0, 0, 2])
        f = rng.uniform(5, 15) * n
        v = 0.05 * d + 0.002 * f  # compliant response to the contact force
        vs.append(v)
        fs.append(f)
    imp = derive_impedance(np.array(vs), np.array(fs))
    assert imp.direction @ d > 0.999


def test_impedance_bad_input():
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        derive_impedance(np.zeros((5, 2)), np.zeros((5, 2)))
    with pytest.raises(ValueError, match="does not move"):
        derive_impedance(np.zeros((5, 3)), np.ones((5, 3)), in_place_speed=0.0)
    with pytest.raises(ValueError, match="angular_velocities"):
        derive_impedance(np.ones((5, 3)), np.ones((5, 3)), angular_velocities=np.ones((4, 3)))
    with pytest.raises(ValueError, match="positions"):
        derive_impedance(np.ones((5, 3)), np.ones((5, 3)), positions=np.full((5, 3), np.inf))


def test_a_phase_done_in_place_has_its_contact_force_as_the_compliant_axis():
    rng = np.random.default_rng(4)
    v = 0.002 * rng.normal(size=(400, 3))  # a hand holding still, pressing and turning
    f = np.array([1.0, 0.0, 8.0]) + 0.3 * rng.normal(size=(400, 3))
    w = np.array([0.0, 0.0, -0.6]) + 0.01 * rng.normal(size=(400, 3))
    x = np.array([0.55, 0.0, 0.21]) + 0.001 * rng.normal(size=(400, 3))
    imp = derive_impedance(v, f, angular_velocities=w, positions=x)
    assert imp.in_place and imp.mean_speed == 0.0 and imp.n_compliant == 1
    n = np.array([1.0, 0.0, 8.0]) / np.hypot(1.0, 8.0)
    assert abs(imp.compliant_axes[0] @ n) > 0.999
    a = imp.compliant_axes[0]
    np.testing.assert_allclose(imp.stiffness @ a, 100.0 * a, atol=1e-9)  # soft along the press, stiff across
    np.testing.assert_allclose(imp.angular_velocity, [0.0, 0.0, -0.6], atol=0.003)
    np.testing.assert_allclose(imp.mean_position, [0.55, 0.0, 0.21], atol=3e-4)
    np.testing.assert_allclose(np.linalg.det(imp.rotation), 1.0)
    restored = type(imp).from_dict(imp.to_dict())
    assert restored.in_place and np.array_equal(restored.angular_velocity, imp.angular_velocity)
    # in free space: no compliant axis, stiff everywhere
    free = derive_impedance(v, 0.1 * rng.normal(size=(400, 3)))
    assert free.in_place and free.n_compliant == 0
    np.testing.assert_allclose(free.stiffness, 2000.0 * np.eye(3), atol=1e-9)
    # a file written before these fields were learned still loads
    old = {k: val for k, val in imp.to_dict().items() if k not in ("angular_velocity", "mean_position", "in_place")}
    legacy = type(imp).from_dict(old)
    assert not legacy.in_place and legacy.mean_position is None and not legacy.angular_velocity.any()
    with pytest.raises(ValueError, match="finite"):
        derive_impedance(np.full((5, 3), np.nan), np.ones((5, 3)))


def test_phase_impedances_per_phase_of_a_model():
    task = make_task(3, seed=0)
    data = sample_demonstrations(task, 2, 300, seed=1)
    imps = phase_impedances(task.model, [(s, f) for s, f, _ in data], dt=0.01)
    assert len(imps) == 3 and all(i is not None for i in imps)
    restored = type(imps[1]).from_dict(imps[1].to_dict())
    np.testing.assert_array_equal(restored.stiffness, imps[1].stiffness)


# ---------------------------------------------------------------- metrics


def test_accuracy_is_invariant_to_relabelling():
    true = np.array([0] * 10 + [1] * 10 + [2] * 10)
    pred = np.array([2] * 10 + [0] * 10 + [1] * 10)
    score = score_segmentation(true, pred, dt=0.01)
    assert score.accuracy == 1.0
    assert score.mapping == {2: 0, 0: 1, 1: 2}
    np.testing.assert_array_equal(score.transition_errors, [0.0, 0.0])
    assert score.spurious_switches == 0 and score.missed_transitions == 0


def test_transition_errors_and_spurious_switches():
    true = np.array([0] * 10 + [1] * 10 + [2] * 10)
    pred = np.array([0] * 13 + [1] * 5 + [0] * 2 + [2] * 10)  # late, then a flicker back
    score = score_segmentation(true, pred, dt=0.1)
    assert score.accuracy == pytest.approx(25 / 30)
    # 0->1 is 3 steps late; 1->2 is never predicted directly (0->2 instead): missed
    np.testing.assert_allclose(score.transition_errors, [0.3])
    assert score.missed_transitions == 1
    assert score.spurious_switches == 2  # 1->0 and 0->2
    assert score.mean_transition_error == pytest.approx(0.3)


def test_scores_over_demonstrations_share_one_mapping():
    trues = [np.array([0] * 5 + [1] * 5), np.array([0] * 3 + [1] * 7)]
    preds = [np.array([1] * 5 + [0] * 5), np.array([1] * 4 + [0] * 6)]
    overall, per = score_demonstrations(trues, preds, dt=1.0)
    assert overall.mapping == {1: 0, 0: 1}
    assert overall.accuracy == pytest.approx(19 / 20)
    np.testing.assert_allclose(overall.transition_errors, [0.0, 1.0])
    assert match_phases(trues[0], preds[0]) == {1: 0, 0: 1}
    with pytest.raises(ValueError, match="equal length"):
        score_segmentation(np.zeros(3, int), np.zeros(4, int))
