"""The KRC side of the arm: the control laws the KUKA controller runs each FRI cycle.

Cartesian impedance (thesis eq. 79), in the tcp frame as FRI defines it:

    tau = J^T (k_c (x_FRI - x_msr) + D(d_c) + F_FRI) + f_dynamics(q, qd)

- ``k_c`` (6,) stiffness [N/m x3, N m/rad x3] along the tcp axes; the pose error
  is the commanded tcp pose seen from the measured one (translation in tcp
  axes, rotation as the log of R_msr^T R_FRI);
- ``D(d_c)``: damping with normalised ratio d_c per axis,
  D_i = 2 d_c,i sqrt(k_c,i Lambda_ii) with Lambda the tcp's operational-space
  inertia (refreshed every ``inertia_period`` cycles: it changes slowly);
- ``F_FRI`` (6,) the superposed wrench (addTcpFT) in the tcp frame;
- ``f_dynamics``: gravity, Coriolis and centrifugal torques from Pinocchio.

``k_c = 0`` and ``F_FRI = 0`` is gravity compensation (kinesthetic teaching);
``gravity_compensation=True`` ignores commands and does exactly that.
POSITION mode: a stiff joint PD towards a rate-limited joint target plus
gravity compensation.  Safety: a joint within ``joint_limit_margin`` of its
limit while moving towards it, a measured external force above
``cartesian_force_limit``, torques saturated for ``torque_saturation_cycles``
cycles, or a non-finite state latch a safety stop: the arm is then held by
stiff joint springs at the pose where it stopped (the brakes, in effect),
until ``reset_safety()``; a non-finite measurement commands zero torque.

``compute`` is the 1 kHz step and allocates nothing
(tests/robot_sim/test_allocation.py): Pinocchio fills its ``data`` in place
(``ArmKinematics.update_dynamics``) and the laws are numba kernels over
preallocated buffers, passed by address (kernel_plumbing.addresses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import pinocchio as pin
from numba import njit

from robot_sim.cycle import FRI_CYCLE_NS
from robot_sim.krc.packets import ControlMode
from kernel_plumbing.addresses import JIT, HoldsAddresses, address, addresses, carray_at, entry, farray_at
from robot_sim.arm.kinematics import ArmKinematics

POSITION, CART_IMP, JNT_IMP = ControlMode.POSITION, ControlMode.CART_IMP, ControlMode.JNT_IMP

_EPS = np.finfo(np.float64).eps
_PREC2 = _EPS ** (1.0 / 3.0)  # Pinocchio's TaylorSeriesExpansion<double>::precision<2>()


class SafetyReason(IntEnum):
    NONE = 0
    JOINT_LIMIT = 1
    CARTESIAN_FORCE = 2
    TORQUE_SATURATION = 3
    NON_FINITE = 4


@dataclass(frozen=True)
class KrcConfig:
    cartesian_force_limit: float = 150.0  # N, on the estimated external force
    joint_limit_margin: float = np.deg2rad(2.0)  # rad
    torque_saturation_cycles: int = 50
    position_kp: tuple = (1500.0, 1500.0, 800.0, 800.0, 300.0, 150.0, 100.0)  # N m/rad
    position_kd: tuple = (60.0, 60.0, 30.0, 30.0, 12.0, 6.0, 4.0)  # N m s/rad
    position_speed_fraction: float = 0.3  # of each joint's maximum speed, towards a target set once
    # JNT_IMP when the remote leaves jntStiffness / jntDamping unflagged (what KRL would have set)
    joint_stiffness: tuple = (1000.0, 1000.0, 1000.0, 1000.0, 500.0, 300.0, 300.0)  # N m/rad
    joint_damping: float = 0.7  # normalised
    hold_stiffness: tuple = (2000.0, 2000.0, 2000.0, 150.0, 150.0, 150.0)  # cartesian hold in MON
    hold_damping: float = 0.7
    inertia_period: int = 10  # cycles between refreshes of Lambda
    # how far a remote's first command in command mode may be from the measured state
    # (robot_sim.cell's check, FRI over UDP): assumptions, not KUKA's figures
    first_command_max_jump_m: float = 0.01
    first_command_max_jump_rad: float = np.deg2rad(3.0)
    cycle_s: float = FRI_CYCLE_NS / 1e9


@dataclass
class ImpedanceCommand:
    """What a CART_IMP cycle needs (the fields of an FRI command packet)."""

    cart_pos: np.ndarray  # (12,) 3x4 row-major tcp pose in the base frame
    cart_stiffness: np.ndarray  # (6,)
    cart_damping: np.ndarray  # (6,) normalised
    add_tcp_ft: np.ndarray  # (6,) [F; T] in the tcp frame


def pose_to_cart_pos(oMtcp: pin.SE3) -> np.ndarray:
    """SE3 -> FRI's 12 numbers (3x4 row-major)."""
    return np.hstack([oMtcp.rotation, oMtcp.translation[:, None]]).ravel()


# --------------------------------------------------------------------------
# kernels: the arithmetic of one cycle (array versions, then the per-step
# entry points that take buffer addresses)
# --------------------------------------------------------------------------


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


def _impedance_work_size(nv: int) -> int:
    """Floats of scratch ``_impedance_at`` carves up: J, error, R_err, log3's,
    then lambda_diagonal's L, X, A, La, y."""
    return 6 * nv + 6 + 9 + 12 + nv * nv + 6 * nv + 36 + 36 + 6


@njit(**JIT)
def _impedance_at(nv, jw_at, rot_at, pos_at, support_at, nle_at, mass_at, qd_at, pose_at, k_at, d_at, ft_at,
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
def _pose_at(rot_at, pos_at, out_at):
    """out = the FRI 12 numbers (3x4 row-major) of the pose (R, p)."""
    R, p, out = farray_at(rot_at, (3, 3)), carray_at(pos_at, (3,)), carray_at(out_at, (12,))
    for i in range(3):
        out[4 * i], out[4 * i + 1], out[4 * i + 2], out[4 * i + 3] = R[i, 0], R[i, 1], R[i, 2], p[i]


@njit(**JIT)
def _joint_spring_at(nv, q_at, qd_at, nle_at, goal_at, kp_at, kd_at, tau_at):
    q, qd, nle = carray_at(q_at, (nv,)), carray_at(qd_at, (nv,)), carray_at(nle_at, (nv,))
    goal, tau = carray_at(goal_at, (nv,)), carray_at(tau_at, (nv,))
    kp, kd = carray_at(kp_at, (nv,)), carray_at(kd_at, (nv,))
    for i in range(nv):
        tau[i] = kp[i] * (goal[i] - q[i]) - kd[i] * qd[i] + nle[i]


@njit(**JIT)
def _rate_limit_at(nv, interp_at, target_at, step_at):
    interp, target, step = carray_at(interp_at, (nv,)), carray_at(target_at, (nv,)), carray_at(step_at, (nv,))
    for i in range(nv):
        interp[i] += min(max(target[i] - interp[i], -step[i]), step[i])


@njit(**JIT)
def _saturate_at(nv, tau_at, max_at, last_at):
    """Clip tau to +-max (into tau and last); True if any joint is at its limit."""
    tau, tau_max, last = carray_at(tau_at, (nv,)), carray_at(max_at, (nv,)), carray_at(last_at, (nv,))
    saturated = False
    for i in range(nv):
        tau[i] = min(max(tau[i], -tau_max[i]), tau_max[i])
        last[i] = tau[i]
        saturated |= abs(tau[i]) >= tau_max[i] * 0.999
    return saturated


@njit(**JIT)
def _state_problem_at(nv, q_at, qd_at, low_at, high_at, check_limits, force_at, has_force, force_limit):
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


# the step's kernels, called as machine code (kernel_plumbing.addresses.entry)
_state_problem = entry(_state_problem_at, f"{addresses(5)}, boolean, int64, boolean, float64")
_impedance_law = entry(_impedance_at, f"{addresses(12)}, boolean, {addresses(4)}")
_pose = entry(_pose_at, addresses(3))
_joint_spring = entry(_joint_spring_at, addresses(8))
_rate_limit = entry(_rate_limit_at, addresses(4))
_saturate = entry(_saturate_at, addresses(4))

_STOP_REASONS = tuple(SafetyReason)  # indexed by _state_problem_at's result
# for the step: in Python 3.11 looking a member up on its Enum class allocates
_SAFE, _NON_FINITE, _TORQUE_SATURATION = SafetyReason.NONE, SafetyReason.NON_FINITE, SafetyReason.TORQUE_SATURATION


class KrcController(HoldsAddresses):
    """Computes joint torques each cycle from the measured state and the FRI outcome.

    The kernels read ``kp``, ``kd``, ``tau_max`` and write ``last_tau``,
    ``last_wrench_tcp`` through addresses taken here: change those arrays in
    place, never rebind them."""

    def __init__(self, kinematics: ArmKinematics, config: KrcConfig = KrcConfig()):
        self.kin = kinematics
        self.config = config
        d = kinematics.description
        self.tau_max = np.array(d.tau_max)
        self.qd_max = np.array(d.qd_max)
        self.q_min, self.q_max = np.array(d.q_min), np.array(d.q_max)
        self._q_low = self.q_min + config.joint_limit_margin
        self._q_high = self.q_max - config.joint_limit_margin
        self.kp = np.array(config.position_kp)
        self.kd = np.array(config.position_kd)
        self.mode = CART_IMP
        self.gravity_compensation = False
        self.safety = SafetyReason.NONE
        self._saturated_cycles = 0
        # the cycle within inertia_period; Lambda is refreshed at phase 1 (and
        # every cycle when the period is 1).  Small ints: CPython caches those
        # up to 256, so counting allocates nothing.
        self._phase = 0
        self._refresh_phase = 1 % config.inertia_period
        self._lambda_diag = np.ones(6)
        self.last_tau = np.zeros(7)
        self.last_wrench_tcp = np.zeros(6)
        # states that used to be None until set: buffers plus a flag
        self._q_hold, self._holding_joints = np.zeros(7), False
        self._x_hold, self._holding_pose = np.zeros(12), False  # FRI's 12 numbers
        self._q_target, self._has_target = np.zeros(7), False
        self._q_interp, self._interpolating = np.zeros(7), False
        # how far the interpolated position target may move per cycle: towards a target set
        # once, a fraction of the joint speed limit; following a target streamed every cycle
        # (FRI's POSITION mode), the limit itself
        self._ptp_step = config.position_speed_fraction * self.qd_max * config.cycle_s
        self._stream_step = self.qd_max * config.cycle_s
        self._position_step = self._ptp_step.copy()
        # JNT_IMP's command: setpoint, stiffness, damping ratio, added torque
        self._jnt_cmd, self._jnt_k = np.zeros(7), np.array(config.joint_stiffness, dtype=np.float64)
        self._jnt_d, self._jnt_trq = np.full(7, config.joint_damping), np.zeros(7)
        self._has_joint_command = False
        self._hold_stiffness = np.array(config.hold_stiffness, dtype=np.float64)
        self._hold_damping = np.full(6, config.hold_damping)
        self._no_wrench = np.zeros(6)
        # this cycle's inputs, copied: the kernels reach buffers by address only
        self._q, self._qd = np.zeros(7), np.zeros(7)
        self._force = np.zeros(3)
        self._pose_cmd = np.zeros(12)
        self._stiffness, self._damping, self._wrench = np.zeros(6), np.zeros(6), np.zeros(6)
        self._tau = np.zeros(7)
        nv = kinematics.model.nv
        self._work = np.zeros(_impedance_work_size(nv))
        self._support = kinematics.support("tcp")
        views = kinematics.views
        rotation, translation = kinematics.frame_views("tcp")
        if not (views["J"].flags.f_contiguous and views["M"].flags.f_contiguous and rotation.flags.f_contiguous):
            raise RuntimeError("expected Pinocchio's data.J, data.M and oMf rotations column-major (Eigen's default)")
        buffers = {"J": views["J"], "M": views["M"], "nle": views["nle"], "R": rotation, "p": translation,
                   "support": self._support, "q": self._q, "qd": self._qd, "force": self._force,
                   "low": self._q_low, "high": self._q_high, "pose": self._pose_cmd, "k": self._stiffness,
                   "d": self._damping, "ft": self._wrench, "hold_pose": self._x_hold, "hold_k": self._hold_stiffness,
                   "hold_d": self._hold_damping, "no_wrench": self._no_wrench, "lam": self._lambda_diag,
                   "work": self._work, "wrench_tcp": self.last_wrench_tcp, "tau": self._tau, "last_tau": self.last_tau,
                   "tau_max": self.tau_max, "kp": self.kp, "kd": self.kd, "q_hold": self._q_hold,
                   "q_target": self._q_target, "q_interp": self._q_interp, "step": self._position_step}
        self._at = {name: address(a) for name, a in buffers.items()}
        self._buffers = buffers  # what the addresses point into, kept alive

    # ------------------------------------------------------------- commands

    def switch_mode(self, mode: int) -> None:
        if mode not in (POSITION, CART_IMP, JNT_IMP):
            raise ValueError(f"control mode {mode} not supported (POSITION=1, CART_IMP=2, JNT_IMP=3)")
        self.mode = ControlMode(mode)
        self._holding_joints = False
        self._holding_pose = False
        self._interpolating = False
        self._has_target = False
        self._has_joint_command = False

    def set_joint_target(self, q_target, streamed: bool = False) -> None:
        """POSITION mode target.  Set once (``streamed=False``) the KRC moves there at
        ``position_speed_fraction`` of the joint speed limit; streamed every cycle (an
        FRI remote's jntPos) it follows the stream, as fast as the speed limit allows."""
        q_target = np.asarray(q_target, dtype=np.float64)
        if q_target.shape != (7,) or not np.all(np.isfinite(q_target)):
            raise ValueError(f"joint target must be 7 finite angles, got {q_target!r}")
        np.clip(q_target, self.q_min + self.config.joint_limit_margin * 2,
                self.q_max - self.config.joint_limit_margin * 2, out=self._q_target)
        self._position_step[...] = self._stream_step if streamed else self._ptp_step
        self._has_target = True

    def set_joint_impedance(self, q_cmd, stiffness=None, damping=None, add_torque=None) -> None:
        """JNT_IMP's command for this cycle (FRI's jntPos, jntStiffness, jntDamping,
        addJntTrq); None keeps the KRC's own value (``KrcConfig.joint_stiffness``,
        ``joint_damping``, no added torque).  The law:
        tau = k (q_cmd - q) - 2 d sqrt(k M_ii) qd + tau_add + f_dynamics(q, qd)."""
        self._jnt_cmd[...] = q_cmd
        self._jnt_k[...] = self.config.joint_stiffness if stiffness is None else stiffness
        self._jnt_d[...] = self.config.joint_damping if damping is None else damping
        self._jnt_trq[...] = 0.0 if add_torque is None else add_torque
        self._has_joint_command = True

    def reset_safety(self) -> None:
        self.safety = SafetyReason.NONE
        self._saturated_cycles = 0
        self._holding_joints = False
        self._holding_pose = False

    # ---------------------------------------------------------------- cycle

    def compute(self, q: np.ndarray, qd: np.ndarray, command: ImpedanceCommand | None = None,
                hold: bool = True, external_force: np.ndarray | None = None) -> np.ndarray:
        """Torques for this cycle.  ``command``: this cycle's FRI command (or the
        repeated last one); ``hold``: no valid command (FRI not in CMD, or too
        many misses): the arm holds its pose.  ``external_force``: the
        estimated external force at the tcp (3,), for the force limit.

        Returns the controller's own (7,) buffer, overwritten by the next call:
        copy it to keep it.  Allocates nothing."""
        self._phase = 0 if self._phase + 1 == self.config.inertia_period else self._phase + 1
        at = self._at
        self._q[...] = q
        self._qd[...] = qd
        has_force = external_force is not None
        if has_force:
            self._force[...] = external_force
        problem = _state_problem(7, at["q"], at["qd"], at["low"], at["high"], self.safety == _SAFE,
                                 at["force"], has_force, self.config.cartesian_force_limit)
        if problem == _NON_FINITE:
            # nothing can be computed from a broken measurement: drives off,
            # brakes on (the physics keeps the arm; no torque is commanded)
            self.safety = _NON_FINITE
            self.last_tau.fill(0.0)
            self._tau.fill(0.0)
            return self._tau
        if problem:
            self._stop(_STOP_REASONS[problem], self._q)
        self.kin.update_dynamics(self._q, self._qd)
        if self.safety != _SAFE:
            self._joint_hold()
        elif self.gravity_compensation:
            self._tau[...] = self.kin.views["nle"]
            self.last_wrench_tcp.fill(0.0)
        elif self.mode == POSITION:
            self._position()
        elif self.mode == JNT_IMP:
            if hold or not self._has_joint_command:
                self._position()  # monitor mode: held where it is, as in POSITION
            else:
                self._joint_impedance()
        elif hold or command is None:
            self._cartesian_hold()
        else:
            self._holding_pose = False
            self._pose_cmd[...] = command.cart_pos
            self._stiffness[...] = command.cart_stiffness
            self._damping[...] = command.cart_damping
            self._wrench[...] = command.add_tcp_ft
            self._impedance(at["pose"], at["k"], at["d"], at["ft"])
        saturated = _saturate(7, at["tau"], at["tau_max"], at["last_tau"])
        if saturated:
            self._saturated_cycles = min(self._saturated_cycles + 1, self.config.torque_saturation_cycles)
        else:
            self._saturated_cycles = 0
        if self._saturated_cycles >= self.config.torque_saturation_cycles and self.safety == _SAFE:
            self._stop(_TORQUE_SATURATION, self._q)
        return self._tau

    # ------------------------------------------------------------------ laws

    def _impedance(self, pose_at, stiffness_at, damping_at, wrench_at):
        at = self._at
        _impedance_law(7, at["J"], at["R"], at["p"], at["support"], at["nle"], at["M"], at["qd"], pose_at,
                       stiffness_at, damping_at, wrench_at, self._phase == self._refresh_phase, at["lam"], at["work"],
                       at["wrench_tcp"], at["tau"])

    def _cartesian_hold(self):
        at = self._at
        if not self._holding_pose:
            _pose(at["R"], at["p"], at["hold_pose"])
            self._holding_pose = True
        self._impedance(at["hold_pose"], at["hold_k"], at["hold_d"], at["no_wrench"])

    def _position(self):
        at = self._at
        if not self._interpolating:
            self._q_interp[...] = self._q
            self._interpolating = True
        if not self._has_target:
            self._q_target[...] = self._q
            self._has_target = True
        _rate_limit(7, at["q_interp"], at["q_target"], at["step"])
        _joint_spring(7, at["q"], at["qd"], at["nle"], at["q_interp"], at["kp"], at["kd"], at["tau"])

    def _joint_impedance(self):
        # not a kernel: JNT_IMP serves remotes over FRI (etar-bench serve), not the
        # allocation-free reproduction loop
        self._interpolating = self._has_target = False  # a later hold holds where it then is
        M = self.kin.views["M"]
        damping = 2.0 * self._jnt_d * np.sqrt(self._jnt_k * np.diag(M))
        self._tau[...] = (self._jnt_k * (self._jnt_cmd - self._q) - damping * self._qd + self._jnt_trq
                          + self.kin.views["nle"])
        self.last_wrench_tcp.fill(0.0)

    def _joint_hold(self):
        at = self._at
        if not self._holding_joints:
            self._q_hold[...] = self._q
            self._holding_joints = True
        _joint_spring(7, at["q"], at["qd"], at["nle"], at["q_hold"], at["kp"], at["kd"], at["tau"])

    # --------------------------------------------------------------- safety

    def _stop(self, reason: SafetyReason, q):
        self.safety = reason
        self._q_hold[...] = q
        self._holding_joints = True

    @property
    def reached_target(self) -> bool:
        """POSITION mode: the interpolated target has arrived at the final target."""
        return (self._has_target and self._interpolating
                and np.allclose(self._q_interp, self._q_target, atol=1e-9))
