"""The 1 ms control step allocates nothing, in every KRC mode.

Two measurements (bench/allocation.py): tracemalloc in this process, for
Python objects, numpy data and numba's runtime; and a malloc counter preloaded
into a child process, for every C and C++ heap block as well (eigenpy,
Pinocchio, MuJoCo).  Pinocchio's own bindings copy each numpy vector argument
into a new Eigen vector; robot_sim.arm._pinocchio_inplace is what removes those.
"""

import runpy
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from robot_sim.arm import kinematics
from robot_sim.arm.kinematics import ArmKinematics

# a measuring tool, not part of the simulation: it lives with the benches
ALLOCATION = runpy.run_path(str(Path(__file__).resolve().parents[2] / "bench" / "allocation.py"))
CONTROL_STEPS, count_mallocs, traced_allocation = (ALLOCATION[n] for n in ("CONTROL_STEPS", "count_mallocs",
                                                                           "traced_allocation"))

STEPS = 2000


@pytest.mark.parametrize("mode", CONTROL_STEPS)
def test_the_control_step_allocates_nothing_python_or_numpy_can_see(mode):
    make, safety = CONTROL_STEPS[mode]
    step, krc = make()
    # tracemalloc sees every thread: a clean run out of three rules out another
    # thread's allocations (what the step allocates, it allocates every run)
    for _ in range(3):
        growth, worst = traced_allocation(step, STEPS)
        if growth == 0 and worst == 0:
            break
    assert krc.safety == safety
    assert growth == 0, f"{mode}: traced memory grew by {growth} B over {STEPS} steps"
    # not one byte: no array, view, numpy scalar or Python object in any step
    assert worst == 0, f"{mode}: a step allocated {worst} B (transient)"


def test_tracemalloc_sees_what_a_step_allocates():
    step, _ = CONTROL_STEPS["cartesian_hold"][0]()
    # a 7-vector (56 B of data and its header), a numpy scalar (24 B and more)
    for extra, at_least in ((lambda: np.empty(7), 56 + 96), (lambda: np.float64(1.0) + 1.0, 24)):
        def allocating(extra=extra):
            step()
            extra()

        _, worst = traced_allocation(allocating, 100)
        assert worst >= at_least


def test_the_control_step_makes_no_c_heap_allocation():
    assert kinematics.PINOCCHIO_INPLACE is not None, kinematics.PINOCCHIO_INPLACE_MISSING
    counts = count_mallocs(STEPS)
    assert set(counts) == set(CONTROL_STEPS)
    for mode, (calls, nbytes) in counts.items():
        assert (calls, nbytes) == (0, 0), f"{mode}: {calls} C allocations ({nbytes} B) over {STEPS} steps"


def test_the_malloc_count_sees_pinocchio_bindings_copy_q_and_qd(monkeypatch):
    # the same steps through Pinocchio's bindings: eigenpy's two 7-vector copies per step
    monkeypatch.setenv("ROBOT_SIM_PINOCCHIO_INPLACE", "0")
    counts = count_mallocs(500, ["cartesian_hold", "cart_imp_on_plate"])
    for mode, (calls, nbytes) in counts.items():
        assert calls == 2 * 500, mode
        assert nbytes == 2 * 500 * 7 * 8, mode


def test_the_inplace_update_leaves_data_as_the_bindings_do():
    native = kinematics.PINOCCHIO_INPLACE
    assert native is not None, kinematics.PINOCCHIO_INPLACE_MISSING
    assert native.PINOCCHIO_VERSION == pin.__version__
    kin = ArmKinematics()
    model, data, reference = kin.model, kin.data, kin.model.createData()
    rng = np.random.default_rng(3)
    for _ in range(25):
        q = rng.uniform(kin.q_min, kin.q_max)
        qd = rng.uniform(-2.0, 2.0, 7)
        native.compute_all_terms(model, data, q, qd)
        pin.computeAllTerms(model, reference, q, qd)
        pin.updateFramePlacements(model, reference)
        for name in ("M", "nle", "J", "g", "C"):
            assert np.array_equal(getattr(data, name), getattr(reference, name)), name
        for fid in kin.frame_ids.values():
            assert np.array_equal(data.oMf[fid].homogeneous, reference.oMf[fid].homogeneous)


def test_the_inplace_update_takes_any_float_vector_and_rejects_a_wrong_size():
    native = kinematics.PINOCCHIO_INPLACE
    assert native is not None, kinematics.PINOCCHIO_INPLACE_MISSING
    kin = ArmKinematics()
    q = np.array([0.3, -0.4, 0.2, 1.2, -0.3, -0.9, 0.5])
    qd = np.linspace(-0.5, 0.5, 7)
    native.compute_all_terms(kin.model, kin.data, q, qd)
    expected = kin.data.nle.copy()
    # a strided view and float32 are copied by eigenpy, not misread
    strided = np.repeat(q, 2)[::2]
    native.compute_all_terms(kin.model, kin.data, strided, qd)
    assert np.array_equal(kin.data.nle, expected)
    native.compute_all_terms(kin.model, kin.data, q, qd.astype(np.float32))
    assert np.allclose(kin.data.nle, expected, atol=1e-5)
    with pytest.raises(ValueError, match="wrong argument size"):
        native.compute_all_terms(kin.model, kin.data, q[:6], qd)
