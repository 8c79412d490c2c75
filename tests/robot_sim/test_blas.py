"""kernel_plumbing.blas: kernels that call numpy's own OpenBLAS get numpy's bits, where a
written-out loop does not (bench/blas_bits.py counts how often)."""

import numpy as np
import pinocchio as pin
import pytest

from kernel_plumbing import blas
from robot_sim import cell
from robot_sim.arm.kinematics import ArmKinematics
from robot_sim.world.tasks import valley

pytestmark = pytest.mark.skipif(not blas.AVAILABLE, reason=f"numpy's OpenBLAS not reachable: {blas.WHY}")


def test_products_through_numpys_library_have_numpys_bits():
    rng = np.random.default_rng(11)
    y6, y3 = np.empty(6), np.empty(3)
    for _ in range(2000):
        J, t = rng.standard_normal((6, 7)), rng.standard_normal(7)
        R, v = rng.standard_normal((3, 3)), rng.standard_normal(3)
        blas.gemv(blas.GEMV, J, t, y6, False)
        assert np.array_equal(y6, J @ t)
        blas.gemv(blas.GEMV, R, v, y3, True)
        assert np.array_equal(y3, R.T @ v)


def test_the_compiled_external_wrench_is_numpys_bit_for_bit():
    assert cell._EXTERNAL_WRENCH is not None  # the import-time check passed here
    rng = np.random.default_rng(12)
    scratch, JJt, Jtau = cell.ExternalWrenchScratch(), np.empty((6, 6)), np.empty(6)
    kin = ArmKinematics()
    differ = 0
    for k in range(3000):
        if k % 2:  # random matrices, and the arm's own Jacobians at random postures
            scratch.jacobian[:], scratch.tau[:] = rng.standard_normal((6, 7)), rng.standard_normal(7)
        else:
            kin.update(rng.uniform(-2.0, 2.0, 7))
            scratch.jacobian[:] = kin.jacobian("tcp", pin.ReferenceFrame.LOCAL)
            scratch.tau[:] = rng.normal(0.0, 5.0, 7)
        expected = cell._external_wrench_numpy(scratch.jacobian, scratch.tau, JJt, Jtau)
        differ += not np.array_equal(scratch.solve(cell._EXTERNAL_WRENCH), expected)
    assert differ == 0


def test_a_cell_estimates_the_external_wrench_as_numpy_does():
    c = cell.RobotCell(valley(), seed=0)
    c.start()
    for _ in range(20):
        c.begin_cycle()
        c.end_cycle(np.array([0.0, 0.0, -5.0, 0.0, 0.0, 0.0]))  # a hand pushing down: a wrench to estimate
        estimate = c.external_wrench_tcp()
        expected = cell._external_wrench_numpy(c.kin.jacobian("tcp", pin.ReferenceFrame.LOCAL), c._tau_ext,
                                               np.empty((6, 6)), np.empty(6))
        assert np.array_equal(estimate, expected)
    assert abs(estimate[2]) > 1.0  # the push is seen, so the comparison compared something
    # a copy: the next cycle's estimate does not overwrite what a caller kept
    kept = c.external_wrench_tcp()
    c.begin_cycle()
    c.end_cycle()
    assert np.array_equal(kept, estimate)


def test_a_nan_jacobian_gives_nan_as_through_numpy():
    # no silent number from garbage: NaN in, NaN out (the cell's finiteness checks then judge)
    scratch = cell.ExternalWrenchScratch()
    scratch.jacobian[:], scratch.tau[:] = np.nan, 1.0
    expected = cell._external_wrench_numpy(scratch.jacobian, scratch.tau, np.empty((6, 6)), np.empty(6))
    assert np.isnan(expected).all() and np.isnan(scratch.solve(cell._EXTERNAL_WRENCH)).all()


def test_a_cell_without_the_kernel_measures_the_same(monkeypatch):
    # where numpy's library is not reachable the cell takes the numpy path: the same packets
    def measurements():
        c = cell.RobotCell(valley(), seed=3)
        c.start()
        out = []
        for _ in range(30):
            out.append(c.begin_cycle().est_ext_tcp_ft.copy())
            c.end_cycle(np.array([1.0, -2.0, -5.0, 0.0, 0.1, 0.0]))
        return np.array(out)

    compiled = measurements()
    monkeypatch.setattr(cell, "_EXTERNAL_WRENCH", None)
    assert np.array_equal(measurements(), compiled)
    assert np.abs(compiled[-1, :3]).max() > 1.0


def test_a_singular_system_gives_nan_as_numpys_solve_kernel_does():
    # two equal rows of 1e8: J J^T + 1e-9 I keeps them equal in float64, exactly singular
    scratch = cell.ExternalWrenchScratch()
    scratch.jacobian[:], scratch.tau[:] = 0.0, 1.0
    scratch.jacobian[0, 0] = scratch.jacobian[1, 0] = 1e8
    with np.errstate(invalid="ignore"):
        expected = cell._external_wrench_numpy(scratch.jacobian, scratch.tau, np.empty((6, 6)), np.empty(6))
    assert np.isnan(expected).all()
    assert np.isnan(scratch.solve(cell._EXTERNAL_WRENCH)).all() and scratch.ints[4] > 0
