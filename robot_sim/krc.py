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
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import pinocchio as pin

from robot_sim.fri import ControlMode
from robot_sim.kinematics import ArmKinematics

POSITION, CART_IMP = ControlMode.POSITION, ControlMode.CART_IMP


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
    position_speed_fraction: float = 0.3  # of each joint's maximum speed
    hold_stiffness: tuple = (2000.0, 2000.0, 2000.0, 150.0, 150.0, 150.0)  # cartesian hold in MON
    hold_damping: float = 0.7
    inertia_period: int = 10  # cycles between refreshes of Lambda
    cycle_s: float = 0.001


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


def cart_pos_to_pose(cart_pos) -> pin.SE3:
    m = np.asarray(cart_pos, dtype=np.float64).reshape(3, 4)
    return pin.SE3(m[:, :3].copy(), m[:, 3].copy())


class KrcController:
    """Computes joint torques each cycle from the measured state and the FRI outcome."""

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
        self._cycle = 0
        self._lambda_diag = np.ones(6)
        self._q_hold: np.ndarray | None = None
        self._x_hold: pin.SE3 | None = None
        self._q_target: np.ndarray | None = None
        self._q_interp: np.ndarray | None = None
        self.last_tau = np.zeros(7)
        self.last_wrench_tcp = np.zeros(6)

    # ------------------------------------------------------------- commands

    def switch_mode(self, mode: int) -> None:
        if mode not in (POSITION, CART_IMP):
            raise ValueError(f"control mode {mode} not supported (POSITION=1, CART_IMP=2)")
        self.mode = ControlMode(mode)
        self._q_hold = None
        self._x_hold = None
        self._q_interp = None

    def set_joint_target(self, q_target) -> None:
        """POSITION mode target; the KRC moves there at a limited joint speed."""
        q_target = np.asarray(q_target, dtype=np.float64)
        if q_target.shape != (7,) or not np.all(np.isfinite(q_target)):
            raise ValueError(f"joint target must be 7 finite angles, got {q_target!r}")
        self._q_target = np.clip(q_target, self.q_min + self.config.joint_limit_margin * 2,
                                 self.q_max - self.config.joint_limit_margin * 2)

    def reset_safety(self) -> None:
        self.safety = SafetyReason.NONE
        self._saturated_cycles = 0
        self._q_hold = None
        self._x_hold = None

    # ---------------------------------------------------------------- cycle

    def compute(self, q: np.ndarray, qd: np.ndarray, command: ImpedanceCommand | None = None,
                hold: bool = True, external_force: np.ndarray | None = None) -> np.ndarray:
        """Torques for this cycle.  ``command``: this cycle's FRI command (or the
        repeated last one); ``hold``: no valid command (FRI not in CMD, or too
        many misses): the arm holds its pose.  ``external_force``: the
        estimated external force at the tcp (3,), for the force limit."""
        self._cycle += 1
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
            # nothing can be computed from a broken measurement: drives off,
            # brakes on (the physics keeps the arm; no torque is commanded)
            self.safety = SafetyReason.NON_FINITE
            self.last_tau[:] = 0.0
            return np.zeros(7)
        if self.safety == SafetyReason.NONE:
            self._check_limits(q, qd, external_force)
        self.kin.update(q, qd)
        nle = self.kin.nonlinear_effects(q, qd)
        if self.safety != SafetyReason.NONE:
            tau = self._joint_hold(q, qd, nle)
        elif self.gravity_compensation:
            tau = nle.copy()
            self.last_wrench_tcp[:] = 0.0
        elif self.mode == POSITION:
            tau = self._position(q, qd, nle)
        elif hold or command is None:
            tau = self._cartesian_hold(q, qd, nle)
        else:
            self._x_hold = None
            tau = self._impedance(q, qd, nle, cart_pos_to_pose(command.cart_pos), command.cart_stiffness,
                                  command.cart_damping, command.add_tcp_ft)
        np.clip(tau, -self.tau_max, self.tau_max, out=tau)
        saturated = np.any(np.abs(tau) >= self.tau_max * 0.999)
        self._saturated_cycles = self._saturated_cycles + 1 if saturated else 0
        if self._saturated_cycles >= self.config.torque_saturation_cycles and self.safety == SafetyReason.NONE:
            self._stop(SafetyReason.TORQUE_SATURATION, q)
        np.copyto(self.last_tau, tau)
        return tau

    # ------------------------------------------------------------------ laws

    def _impedance(self, q, qd, nle, oMcmd, stiffness, damping, wrench):
        kin = self.kin
        oMtcp = kin.placement("tcp")
        J = kin.jacobian("tcp", pin.ReferenceFrame.LOCAL)  # twist of the tcp in tcp axes
        error = np.empty(6)
        error[:3] = oMtcp.rotation.T @ (oMcmd.translation - oMtcp.translation)
        error[3:] = pin.log3(oMtcp.rotation.T @ oMcmd.rotation)
        if self._cycle % self.config.inertia_period == 1 or self.config.inertia_period == 1:
            self._refresh_inertia(q)
        twist = J @ qd
        k = np.asarray(stiffness, dtype=np.float64)
        d = 2.0 * np.asarray(damping, dtype=np.float64) * np.sqrt(k * self._lambda_diag)
        F = k * error - d * twist + np.asarray(wrench, dtype=np.float64)
        np.copyto(self.last_wrench_tcp, F)
        return J.T @ F + nle

    def _refresh_inertia(self, q):
        Lam = self.kin.cartesian_mass(q, "tcp")  # LOCAL_WORLD_ALIGNED axes
        R = self.kin.placement("tcp").rotation
        Rb = np.zeros((6, 6))
        Rb[:3, :3] = R
        Rb[3:, 3:] = R
        self._lambda_diag = np.maximum(np.diag(Rb.T @ Lam @ Rb), 1e-3)
        self.kin.update(q)  # cartesian_mass left data at q without velocities

    def _cartesian_hold(self, q, qd, nle):
        if self._x_hold is None:
            self._x_hold = self.kin.placement("tcp")
        c = self.config
        k = np.array(c.hold_stiffness)
        return self._impedance(q, qd, nle, self._x_hold, k, np.full(6, c.hold_damping), np.zeros(6))

    def _position(self, q, qd, nle):
        if self._q_interp is None:
            self._q_interp = q.copy()
        if self._q_target is None:
            self._q_target = q.copy()
        step = self.config.position_speed_fraction * self.qd_max * self.config.cycle_s
        self._q_interp += np.clip(self._q_target - self._q_interp, -step, step)
        return self.kp * (self._q_interp - q) - self.kd * qd + nle

    def _joint_hold(self, q, qd, nle):
        if self._q_hold is None:
            self._q_hold = q.copy()
        return self.kp * (self._q_hold - q) - self.kd * qd + nle

    # --------------------------------------------------------------- safety

    def _check_limits(self, q, qd, external_force):
        if ((q < self._q_low) & (qd < 0)).any() or ((q > self._q_high) & (qd > 0)).any():
            self._stop(SafetyReason.JOINT_LIMIT, q)
        elif external_force is not None and np.linalg.norm(external_force) > self.config.cartesian_force_limit:
            self._stop(SafetyReason.CARTESIAN_FORCE, q)

    def _stop(self, reason: SafetyReason, q):
        self.safety = reason
        self._q_hold = np.array(q, dtype=np.float64)

    @property
    def reached_target(self) -> bool:
        """POSITION mode: the interpolated target has arrived at the final target."""
        return (self._q_target is not None and self._q_interp is not None
                and np.allclose(self._q_interp, self._q_target, atol=1e-9))
