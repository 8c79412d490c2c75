"""The arithmetic of one step of the KRC's laws (robot_sim.krc.law), as numba kernels on
preallocated buffers: the tcp Jacobian from Pinocchio's joint Jacobians, SO(3)'s log, the
operational-space inertia's diagonal, the Cartesian impedance law (thesis eq. 79), the
joint spring, the rate limit, the torque limit and the checks of the measured state.
The functions ending in ``_at`` take the buffers by address (kernel_plumbing.addresses);
none keeps any state.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from kernel_plumbing.addresses import JIT, carray_at, farray_at

_EPS = np.finfo(np.float64).eps
_PREC2 = _EPS ** (1.0 / 3.0)  # Pinocchio's TaylorSeriesExpansion<double>::precision<2>()


@njit(**JIT)
def frame_jacobian(J_world, rotation, translation, support, local, out):
    """A frame's (6, nv) Jacobian [linear; angular] from Pinocchio's joint
    Jacobians (``data.J``: world frame, about the world origin), the frame's
    pose and its ``support`` mask (``ArmKinematics.support``):
    LOCAL_WORLD_ALIGNED  [J_lin - p x J_ang; J_ang],  LOCAL  R^T times that."""
    p, R = translation, rotation
    for j in range(J_world.shape[1]):
        s = support[j]
        wx, wy, wz = J_world[3, j] * s, J_world[4, j] * s, J_world[5, j] * s
        vx = J_world[0, j] * s - (p[1] * wz - p[2] * wy)
        vy = J_world[1, j] * s - (p[2] * wx - p[0] * wz)
        vz = J_world[2, j] * s - (p[0] * wy - p[1] * wx)
        if local:
            for i in range(3):
                out[i, j] = R[0, i] * vx + R[1, i] * vy + R[2, i] * vz
                out[3 + i, j] = R[0, i] * wx + R[1, i] * wy + R[2, i] * wz
        else:
            out[0, j], out[1, j], out[2, j] = vx, vy, vz
            out[3, j], out[4, j], out[5, j] = wx, wy, wz


@njit(**JIT)
def _theta_axis(i0, val, R, axis):
    """Pinocchio's internal::compute_theta_axis: log3 near theta = pi."""
    i1, i2 = (i0 + 1) % 3, (i0 + 2) % 3
    s = math.sqrt(val + _EPS + _EPS * _EPS) * (1.0 if R[i2, i1] >= R[i1, i2] else -1.0)
    axis[i0] = s / 2.0
    axis[i1] = 1.0 / (2.0 * s) * (R[i1, i0] + R[i0, i1])
    axis[i2] = 1.0 / (2.0 * s) * (R[i2, i0] + R[i0, i2])
    w = 1.0 / (2.0 * s) * (R[i2, i1] - R[i1, i2])
    norm = math.sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2])
    axis[0] /= norm
    axis[1] /= norm
    axis[2] /= norm
    return 2.0 * math.atan2(norm, w)


@njit(**JIT)
def log3(R, work, out):
    """out = pin.log3(R) without the allocations, Pinocchio's algorithm
    (log3_impl) including its renormalisation of R.  ``work``: (4, 3) scratch."""
    # renormalize_rotation_matrix: c0, c1 normalised, c2 = c0 x c1, c0 = c1 x c2
    n0 = math.sqrt(R[0, 0] * R[0, 0] + R[1, 0] * R[1, 0] + R[2, 0] * R[2, 0])
    n1 = math.sqrt(R[0, 1] * R[0, 1] + R[1, 1] * R[1, 1] + R[2, 1] * R[2, 1])
    x0, y0, z0 = R[0, 0] / n0, R[1, 0] / n0, R[2, 0] / n0
    x1, y1, z1 = R[0, 1] / n1, R[1, 1] / n1, R[2, 1] / n1
    x2, y2, z2 = y0 * z1 - z0 * y1, z0 * x1 - x0 * z1, x0 * y1 - y0 * x1
    x0, y0, z0 = y1 * z2 - z1 * y2, z1 * x2 - x1 * z2, x1 * y2 - y1 * x2
    tr = x0 + y1 + z2
    cos_value = (tr - 1.0) / 2.0
    if cos_value < -1.0 + _PREC2:  # theta near pi: the axis from the largest diagonal entry
        Rn, axis = work[:3], work[3]
        Rn[0, 0], Rn[0, 1], Rn[0, 2] = x0, x1, x2
        Rn[1, 0], Rn[1, 1], Rn[1, 2] = y0, y1, y2
        Rn[2, 0], Rn[2, 1], Rn[2, 2] = z0, z1, z2
        v0, v1, v2 = 2.0 * x0 - tr + 1.0, 2.0 * y1 - tr + 1.0, 2.0 * z2 - tr + 1.0
        if v0 >= v1:
            i0, val = (0, v0) if v0 >= v2 else (2, v2)
        else:
            i0, val = (1, v1) if v1 >= v2 else (2, v2)
        theta = _theta_axis(i0, val, Rn, axis)
        out[0], out[1], out[2] = theta * axis[0], theta * axis[1], theta * axis[2]
        return
    acos_expansion = math.sqrt(2.0 * (1.0 - cos_value) + _EPS * _EPS)
    if tr <= 3.0 - _PREC2:
        theta = math.acos(cos_value) if tr >= -1.0 + _PREC2 else math.pi - acos_expansion
    else:
        theta = acos_expansion
    a0, a1, a2 = 0.5 * (z1 - y2), 0.5 * (x2 - z0), 0.5 * (y0 - x1)  # unSkew
    n2 = a0 * a0 + a1 * a1 + a2 * a2
    t = theta / math.sin(theta) if theta >= _PREC2 else 1.0 + n2 / 6.0 + n2 * n2 * 3.0 / 40.0
    out[0], out[1], out[2] = t * a0, t * a1, t * a2


@njit(**JIT)
def _cholesky(A, L, upper):
    """L lower triangular with L L^T = A, from A's upper (or lower) triangle."""
    n = A.shape[0]
    for j in range(n):
        for i in range(j):
            L[i, j] = 0.0
        for i in range(j, n):
            acc = A[j, i] if upper else A[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = math.sqrt(acc) if i == j else acc / L[j, j]


@njit(**JIT)
def lambda_diagonal(M, J, L, X, A, La, y, out):
    """out = max(diag(Lambda), 1e-3) with Lambda = (J M^-1 J^T + 1e-9 I)^-1
    the operational-space inertia in J's axes, through Cholesky factors
    (M's upper triangle is read).  Scratch: L (nv, nv), X (nv, 6), A and La
    (6, 6), y (6,)."""
    nv = M.shape[0]
    _cholesky(M, L, True)
    for c in range(6):  # X = M^-1 J^T: L z = J^T, then L^T x = z
        for i in range(nv):
            acc = J[c, i]
            for k in range(i):
                acc -= L[i, k] * X[k, c]
            X[i, c] = acc / L[i, i]
        for i in range(nv - 1, -1, -1):
            acc = X[i, c]
            for k in range(i + 1, nv):
                acc -= L[k, i] * X[k, c]
            X[i, c] = acc / L[i, i]
    for r in range(6):
        for c in range(6):
            acc = 0.0
            for k in range(nv):
                acc += J[r, k] * X[k, c]
            A[r, c] = acc
        A[r, r] += 1e-9
    _cholesky(A, La, False)
    for i in range(6):  # (A^-1)_ii = |La^-1 e_i|^2
        for r in range(6):
            acc = 1.0 if r == i else 0.0
            for k in range(r):
                acc -= La[r, k] * y[k]
            y[r] = acc / La[r, r]
        acc = 0.0
        for r in range(6):
            acc += y[r] * y[r]
        out[i] = max(acc, 1e-3)


def impedance_work_size(nv: int) -> int:
    """Floats of scratch ``impedance_at`` carves up: J, error, R_err, log3's,
    then lambda_diagonal's L, X, A, La, y."""
    return 6 * nv + 6 + 9 + 12 + nv * nv + 6 * nv + 36 + 36 + 6


@njit(**JIT)
def impedance_at(nv, jw_at, rot_at, pos_at, support_at, nle_at, mass_at, qd_at, pose_at, k_at, d_at, ft_at,
                  refresh, lambda_at, work_at, wrench_at, tau_at):
    """Eq. 79 in the tcp frame: the wrench F (into wrench) and tau = J^T F + nle."""
    R, p = farray_at(rot_at, (3, 3)), carray_at(pos_at, (3,))
    pose = carray_at(pose_at, (12,))
    qd, nle = carray_at(qd_at, (nv,)), carray_at(nle_at, (nv,))
    k, d, ft = carray_at(k_at, (6,)), carray_at(d_at, (6,)), carray_at(ft_at, (6,))
    lam, F, tau = carray_at(lambda_at, (6,)), carray_at(wrench_at, (6,)), carray_at(tau_at, (nv,))
    at = work_at  # bytes
    J = carray_at(at, (6, nv))  # maps qd to the tcp's twist in tcp axes
    at += 8 * 6 * nv
    error = carray_at(at, (6,))
    at += 8 * 6
    R_err = carray_at(at, (3, 3))
    at += 8 * 9
    log_work = carray_at(at, (4, 3))
    at += 8 * 12
    L = carray_at(at, (nv, nv))
    at += 8 * nv * nv
    X = carray_at(at, (nv, 6))
    at += 8 * 6 * nv
    A = carray_at(at, (6, 6))
    at += 8 * 36
    La = carray_at(at, (6, 6))
    at += 8 * 36
    y = carray_at(at, (6,))
    frame_jacobian(farray_at(jw_at, (6, nv)), R, p, carray_at(support_at, (nv,)), True, J)
    # the commanded pose seen from the measured one: R^T (p_cmd - p), log(R^T R_cmd)
    for i in range(3):
        error[i] = R[0, i] * (pose[3] - p[0]) + R[1, i] * (pose[7] - p[1]) + R[2, i] * (pose[11] - p[2])
        for j in range(3):
            R_err[i, j] = R[0, i] * pose[j] + R[1, i] * pose[4 + j] + R[2, i] * pose[8 + j]
    log3(R_err, log_work, error[3:])
    if refresh:
        lambda_diagonal(farray_at(mass_at, (nv, nv)), J, L, X, A, La, y, lam)
    for i in range(6):
        twist = 0.0
        for j in range(nv):
            twist += J[i, j] * qd[j]
        F[i] = k[i] * error[i] - 2.0 * d[i] * math.sqrt(k[i] * lam[i]) * twist + ft[i]
    for j in range(nv):
        acc = 0.0
        for i in range(6):
            acc += J[i, j] * F[i]
        tau[j] = acc + nle[j]


@njit(**JIT)
def pose_at(rot_at, pos_at, out_at):
    """out = the FRI 12 numbers (3x4 row-major) of the pose (R, p)."""
    R, p, out = farray_at(rot_at, (3, 3)), carray_at(pos_at, (3,)), carray_at(out_at, (12,))
    for i in range(3):
        out[4 * i], out[4 * i + 1], out[4 * i + 2], out[4 * i + 3] = R[i, 0], R[i, 1], R[i, 2], p[i]


@njit(**JIT)
def joint_spring_at(nv, q_at, qd_at, nle_at, goal_at, kp_at, kd_at, tau_at):
    q, qd, nle = carray_at(q_at, (nv,)), carray_at(qd_at, (nv,)), carray_at(nle_at, (nv,))
    goal, tau = carray_at(goal_at, (nv,)), carray_at(tau_at, (nv,))
    kp, kd = carray_at(kp_at, (nv,)), carray_at(kd_at, (nv,))
    for i in range(nv):
        tau[i] = kp[i] * (goal[i] - q[i]) - kd[i] * qd[i] + nle[i]


@njit(**JIT)
def rate_limit_at(nv, interp_at, target_at, step_at):
    interp, target, step = carray_at(interp_at, (nv,)), carray_at(target_at, (nv,)), carray_at(step_at, (nv,))
    for i in range(nv):
        interp[i] += min(max(target[i] - interp[i], -step[i]), step[i])


@njit(**JIT)
def saturate_at(nv, tau_at, max_at, last_at):
    """Clip tau to +-max (into tau and last); True if any joint is at its limit."""
    tau, tau_max, last = carray_at(tau_at, (nv,)), carray_at(max_at, (nv,)), carray_at(last_at, (nv,))
    saturated = False
    for i in range(nv):
        tau[i] = min(max(tau[i], -tau_max[i]), tau_max[i])
        last[i] = tau[i]
        saturated |= abs(tau[i]) >= tau_max[i] * 0.999
    return saturated


@njit(**JIT)
def state_problem_at(nv, q_at, qd_at, low_at, high_at, check_limits, force_at, has_force, force_limit):
    """The SafetyReason the measured state calls for (NONE = 0)."""
    q, qd = carray_at(q_at, (nv,)), carray_at(qd_at, (nv,))
    for i in range(nv):
        if not (np.isfinite(q[i]) and np.isfinite(qd[i])):
            return 4  # NON_FINITE
    if not check_limits:
        return 0
    low, high = carray_at(low_at, (nv,)), carray_at(high_at, (nv,))
    for i in range(nv):
        if (q[i] < low[i] and qd[i] < 0) or (q[i] > high[i] and qd[i] > 0):
            return 1  # JOINT_LIMIT
    if has_force:
        f = carray_at(force_at, (3,))
        if math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]) > force_limit:
            return 2  # CARTESIAN_FORCE
    return 0
