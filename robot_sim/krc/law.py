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
preallocated buffers, passed by address (kernel_plumbing.addresses): their
arithmetic in robot_sim.krc.law_arithmetic, the step's logic here (which law,
the holds, the safety stops), its state between steps in one int64 array.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import pinocchio as pin
from numba import njit

from robot_sim.cycle import FRI_CYCLE_NS
from robot_sim.krc.packets import (FRI_AXIS_ORDER, CommandPacket, ControlMode, MeasurementExtras, MeasurementPacket,
                                   fri_order)
from kernel_plumbing.addresses import (JIT, HoldsAddresses, address, addresses, carray_at, copy_at, entry,
                                       int64_address, int64_array_at)
from robot_sim.arm.kinematics import COMPUTE_ALL_TERMS, ArmKinematics, call_compute_all_terms
from robot_sim.krc.law_arithmetic import (impedance_at, impedance_work_size, joint_spring_at, pose_at, rate_limit_at,
                                          saturate_at, state_problem_at)

POSITION, CART_IMP, JNT_IMP = ControlMode.POSITION, ControlMode.CART_IMP, ControlMode.JNT_IMP



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


# The controller's state between steps (``KrcController._state``, int64), by index: the
# cycle within inertia_period, the latched SafetyReason, the cycles of saturated torque,
# the holds and targets in force, the control mode, gravity compensation; then three
# settings the kernels read.
(_PHASE, _SAFETY, _SATURATED, _HOLDING_JOINTS, _HOLDING_POSE, _HAS_TARGET, _INTERPOLATING, _MODE, _GRAVITY,
 _HAS_JOINT_COMMAND, _INERTIA_PERIOD, _REFRESH_PHASE, _SATURATION_CYCLES) = range(13)
_STATE_SIZE = 13
# The buffers the kernels reach, in the controller's address table (``KrcController._table``)
BUFFERS = ("J", "M", "nle", "R", "p", "support", "q", "qd", "force", "low", "high", "pose", "k", "d", "ft",
           "hold_pose", "hold_k", "hold_d", "no_wrench", "lam", "work", "wrench_tcp", "tau", "last_tau", "tau_max",
           "kp", "kd", "q_hold", "q_target", "q_interp", "step")
(_J, _M, _NLE, _R, _P, _SUPPORT, _Q, _QD, _FORCE, _LOW, _HIGH, _POSE, _K, _D, _FT, _HOLD_POSE, _HOLD_K, _HOLD_D,
 _NO_WRENCH, _LAM, _WORK, _WRENCH_TCP, _TAU, _LAST_TAU, _TAU_MAX, _KP, _KD, _Q_HOLD, _Q_TARGET, _Q_INTERP,
 _STEP) = range(len(BUFFERS))
_NV = 7
# what law_cycle_at returns: the torques are in tau; JNT_IMP's law is the caller's (numpy),
# then law_end_at; Pinocchio failed (the torques are not computed)
LAW_DONE, LAW_JOINT_IMPEDANCE, LAW_DYNAMICS_FAILED = 0, 1, 2


@njit(**JIT)
def _stop_at(s, at, reason):
    """Latch a safety stop: the arm held by stiff joint springs where it is now."""
    s[_SAFETY] = reason
    copy_at(at[_Q], at[_Q_HOLD], _NV)
    s[_HOLDING_JOINTS] = 1


@njit(**JIT)
def law_begin_at(state_at, table_at, q_at, qd_at, force_at, has_force, force_limit):
    """The step's start: the inertia phase advances, the measured state (and the estimated
    external force) is copied in and checked.  False: the state is not finite, the drives
    get zero torque and the step is over."""
    s, at = int64_array_at(state_at, _STATE_SIZE), int64_array_at(table_at, len(BUFFERS))
    s[_PHASE] = 0 if s[_PHASE] + 1 == s[_INERTIA_PERIOD] else s[_PHASE] + 1
    copy_at(q_at, at[_Q], _NV)
    copy_at(qd_at, at[_QD], _NV)
    if has_force:
        copy_at(force_at, at[_FORCE], 3)
    problem = state_problem_at(_NV, at[_Q], at[_QD], at[_LOW], at[_HIGH], s[_SAFETY] == 0, at[_FORCE], has_force,
                                force_limit)
    if problem == 4:  # NON_FINITE: nothing can be computed from a broken measurement
        s[_SAFETY] = 4
        last, tau = carray_at(at[_LAST_TAU], (_NV,)), carray_at(at[_TAU], (_NV,))
        last[:] = 0.0
        tau[:] = 0.0
        return False
    if problem:
        _stop_at(s, at, problem)
    return True


@njit(**JIT)
def _impedance_with(s, at, pose_at, k_at, d_at, ft_at):
    impedance_at(_NV, at[_J], at[_R], at[_P], at[_SUPPORT], at[_NLE], at[_M], at[_QD], pose_at, k_at, d_at, ft_at,
                  s[_PHASE] == s[_REFRESH_PHASE], at[_LAM], at[_WORK], at[_WRENCH_TCP], at[_TAU])


@njit(**JIT)
def _position_with(s, at):
    """POSITION: a stiff joint PD towards the rate-limited target (the arm's own pose if none)."""
    if not s[_INTERPOLATING]:
        copy_at(at[_Q], at[_Q_INTERP], _NV)
        s[_INTERPOLATING] = 1
    if not s[_HAS_TARGET]:
        copy_at(at[_Q], at[_Q_TARGET], _NV)
        s[_HAS_TARGET] = 1
    rate_limit_at(_NV, at[_Q_INTERP], at[_Q_TARGET], at[_STEP])
    joint_spring_at(_NV, at[_Q], at[_QD], at[_NLE], at[_Q_INTERP], at[_KP], at[_KD], at[_TAU])


@njit(**JIT)
def law_torques_at(state_at, table_at, hold, has_command):
    """The torques of the law in force, into tau, once Pinocchio's dynamics terms are
    current.  ``hold``: no usable FRI command; ``has_command``: the command's pose,
    stiffness, damping and wrench are in their buffers.  True: JNT_IMP with a command,
    whose law the caller computes."""
    s, at = int64_array_at(state_at, _STATE_SIZE), int64_array_at(table_at, len(BUFFERS))
    mode = s[_MODE]
    if s[_SAFETY] != 0:
        if not s[_HOLDING_JOINTS]:
            copy_at(at[_Q], at[_Q_HOLD], _NV)
            s[_HOLDING_JOINTS] = 1
        joint_spring_at(_NV, at[_Q], at[_QD], at[_NLE], at[_Q_HOLD], at[_KP], at[_KD], at[_TAU])
    elif s[_GRAVITY]:
        copy_at(at[_NLE], at[_TAU], _NV)
        wrench = carray_at(at[_WRENCH_TCP], (6,))
        wrench[:] = 0.0
    elif mode == 1:  # POSITION
        _position_with(s, at)
    elif mode == 3:  # JNT_IMP: monitor mode holds where it is, as in POSITION
        if hold or not s[_HAS_JOINT_COMMAND]:
            _position_with(s, at)
        else:
            return True
    elif hold or not has_command:  # CART_IMP, held at the pose where the hold began
        if not s[_HOLDING_POSE]:
            pose_at(at[_R], at[_P], at[_HOLD_POSE])
            s[_HOLDING_POSE] = 1
        _impedance_with(s, at, at[_HOLD_POSE], at[_HOLD_K], at[_HOLD_D], at[_NO_WRENCH])
    else:
        s[_HOLDING_POSE] = 0
        _impedance_with(s, at, at[_POSE], at[_K], at[_D], at[_FT])
    return False


@njit(**JIT)
def law_end_at(state_at, table_at):
    """The step's end: tau clipped to the drives' limits (into last_tau too); torques
    saturated for torque_saturation_cycles latch a stop."""
    s, at = int64_array_at(state_at, _STATE_SIZE), int64_array_at(table_at, len(BUFFERS))
    if saturate_at(_NV, at[_TAU], at[_TAU_MAX], at[_LAST_TAU]):
        s[_SATURATED] = min(s[_SATURATED] + 1, s[_SATURATION_CYCLES])
    else:
        s[_SATURATED] = 0
    if s[_SATURATED] >= s[_SATURATION_CYCLES] and s[_SAFETY] == 0:
        _stop_at(s, at, 3)  # TORQUE_SATURATION


@njit(**JIT)
def law_cycle_at(state_at, table_at, q_at, qd_at, force_at, has_force, force_limit, hold, has_command,
                 dynamics_fn, model_at, data_at):
    """One step of the law in one call, Pinocchio's dynamics terms included
    (robot_sim.arm.kinematics.COMPUTE_ALL_TERMS at ``dynamics_fn``): law_begin_at, the
    dynamics at the copied state, law_torques_at, law_end_at.  Returns LAW_DONE,
    LAW_JOINT_IMPEDANCE (then the caller's law and law_end_at) or LAW_DYNAMICS_FAILED."""
    if not law_begin_at(state_at, table_at, q_at, qd_at, force_at, has_force, force_limit):
        return LAW_DONE
    at = int64_array_at(table_at, len(BUFFERS))
    if call_compute_all_terms(dynamics_fn, model_at, data_at, at[_Q], at[_QD]) != 0:
        return LAW_DYNAMICS_FAILED
    if law_torques_at(state_at, table_at, hold, has_command):
        return LAW_JOINT_IMPEDANCE
    law_end_at(state_at, table_at)
    return LAW_DONE


# the step's kernels, called as machine code (kernel_plumbing.addresses.entry)
_law_begin = entry(law_begin_at, f"{addresses(5)}, boolean, float64")
_law_torques = entry(law_torques_at, f"{addresses(2)}, boolean, boolean")
_law_end = entry(law_end_at, addresses(2))
_law_cycle = entry(law_cycle_at, f"{addresses(5)}, boolean, float64, boolean, boolean, {addresses(3)}") \
    if COMPUTE_ALL_TERMS else None

_SAFETY_REASONS = tuple(SafetyReason)  # indexed by the state's value: looking a member up allocates
_MODES = {int(m): m for m in ControlMode}


@njit(**JIT)
def _load_applied_at(numbers_at, pose_at, stiffness_at, damping_at, wrench_at):
    """A command's numbers as an FRI link keeps them (robot_sim.krc.link_books' slot: rows
    cart_pos, cart_stiffness, cart_damping, add_tcp_ft, 12 wide; the wrench in FRI's order)
    into the law's buffers (the wrench in the standard order): ``KrcController.load_numbers``
    of the slot's rows, in one call."""
    n = carray_at(numbers_at, (4, 12))
    pose, k, d, w = (carray_at(pose_at, (12,)), carray_at(stiffness_at, (6,)), carray_at(damping_at, (6,)),
                     carray_at(wrench_at, (6,)))
    for i in range(12):
        pose[i] = n[0, i]
    for i in range(6):
        k[i] = n[1, i]
        d[i] = n[2, i]
        w[i] = n[3, FRI_AXIS_ORDER[i]]


_LOAD_APPLIED = entry(_load_applied_at, addresses(5))


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
        # what the kernels keep between steps (the _PHASE ... indices); Lambda is refreshed
        # at phase 1 of inertia_period (and every cycle when the period is 1)
        self._state = np.zeros(_STATE_SIZE, dtype=np.int64)
        self._state[_MODE] = CART_IMP
        self._state[_INERTIA_PERIOD] = config.inertia_period
        self._state[_REFRESH_PHASE] = 1 % config.inertia_period
        self._state[_SATURATION_CYCLES] = config.torque_saturation_cycles
        self._lambda_diag = np.ones(6)
        self.last_tau = np.zeros(7)
        self.last_wrench_tcp = np.zeros(6)
        # the holds and targets, each a buffer and a flag in the state
        self._q_hold = np.zeros(7)
        self._x_hold = np.zeros(12)  # FRI's 12 numbers
        self._q_target = np.zeros(7)
        self._q_interp = np.zeros(7)
        # how far the interpolated position target may move per cycle: towards a target set
        # once, a fraction of the joint speed limit; following a target streamed every cycle
        # (FRI's POSITION mode), the limit itself
        self._ptp_step = config.position_speed_fraction * self.qd_max * config.cycle_s
        self._stream_step = self.qd_max * config.cycle_s
        self._position_step = self._ptp_step.copy()
        # JNT_IMP's command: setpoint, stiffness, damping ratio, added torque
        self._jnt_cmd, self._jnt_k = np.zeros(7), np.array(config.joint_stiffness, dtype=np.float64)
        self._jnt_d, self._jnt_trq = np.full(7, config.joint_damping), np.zeros(7)
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
        self._work = np.zeros(impedance_work_size(nv))
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
        self._table = np.array([self._at[name] for name in BUFFERS], dtype=np.int64)
        self._buffers = buffers  # what the addresses point into, kept alive
        self.state_at, self.table_at = int64_address(self._state), int64_address(self._table)
        self.force_at, self.tau_at = self._at["force"], self._at["tau"]
        self._command_at = (self._at["pose"], self._at["k"], self._at["d"], self._at["ft"])  # load_applied's
        self._model_at, self._data_at = kinematics.native  # the C++ Model and Data, for _law_cycle

    # ------------------------------------------------------------- the state

    @property
    def safety(self) -> SafetyReason:
        return _SAFETY_REASONS[self._state[_SAFETY]]

    @property
    def mode(self) -> ControlMode:
        return _MODES[int(self._state[_MODE])]

    @property
    def gravity_compensation(self) -> bool:
        """Ignore commands and compensate gravity only (kinesthetic teaching)."""
        return bool(self._state[_GRAVITY])

    @gravity_compensation.setter
    def gravity_compensation(self, on: bool) -> None:
        self._state[_GRAVITY] = bool(on)

    # ------------------------------------------------------------- commands

    def switch_mode(self, mode: int) -> None:
        if mode not in (POSITION, CART_IMP, JNT_IMP):
            raise ValueError(f"control mode {mode} not supported (POSITION=1, CART_IMP=2, JNT_IMP=3)")
        s = self._state
        s[_MODE] = ControlMode(mode)
        s[_HOLDING_JOINTS] = s[_HOLDING_POSE] = s[_INTERPOLATING] = s[_HAS_TARGET] = s[_HAS_JOINT_COMMAND] = 0

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
        self._state[_HAS_TARGET] = 1

    def set_joint_impedance(self, q_cmd, stiffness=None, damping=None, add_torque=None) -> None:
        """JNT_IMP's command for this cycle (FRI's jntPos, jntStiffness, jntDamping,
        addJntTrq); None keeps the KRC's own value (``KrcConfig.joint_stiffness``,
        ``joint_damping``, no added torque).  The law:
        tau = k (q_cmd - q) - 2 d sqrt(k M_ii) qd + tau_add + f_dynamics(q, qd)."""
        self._jnt_cmd[...] = q_cmd
        self._jnt_k[...] = self.config.joint_stiffness if stiffness is None else stiffness
        self._jnt_d[...] = self.config.joint_damping if damping is None else damping
        self._jnt_trq[...] = 0.0 if add_torque is None else add_torque
        self._state[_HAS_JOINT_COMMAND] = 1

    def reset_safety(self) -> None:
        s = self._state
        s[_SAFETY] = s[_SATURATED] = s[_HOLDING_JOINTS] = s[_HOLDING_POSE] = 0

    # ---------------------------------------------------------------- cycle

    def compute(self, q: np.ndarray, qd: np.ndarray, command: ImpedanceCommand | None = None,
                hold: bool = True, external_force: np.ndarray | None = None) -> np.ndarray:
        """Torques for this cycle.  ``command``: this cycle's FRI command (or the
        repeated last one); ``hold``: no valid command (FRI not in CMD, or too
        many misses): the arm holds its pose.  ``external_force``: the
        estimated external force at the tcp (3,), for the force limit.

        Returns the controller's own (7,) buffer, overwritten by the next call:
        copy it to keep it.  Allocates nothing."""
        has_force, has_command = external_force is not None, command is not None
        self.load(command, external_force)
        self._q[...] = q
        self._qd[...] = qd
        self.step_at(self._at["q"], self._at["qd"], has_force, hold, has_command)
        return self._tau

    def load(self, command: ImpedanceCommand | None, external_force: np.ndarray | None) -> None:
        """This cycle's command and estimated external force into the buffers the step reads
        (None: none; the step is told which it has)."""
        if external_force is not None:
            self._force[...] = external_force
        if command is not None:
            self.load_numbers(command.cart_pos, command.cart_stiffness, command.cart_damping, command.add_tcp_ft)

    def load_applied(self, numbers_at: int) -> None:
        """``load_numbers`` of a command as an FRI link keeps it, at ``numbers_at`` (``_load_applied_at``)."""
        _LOAD_APPLIED(numbers_at, *self._command_at)

    def load_numbers(self, cart_pos, cart_stiffness, cart_damping, add_tcp_ft) -> None:
        """``load``'s command as its four vectors (add_tcp_ft [F; T], the law's order)."""
        self._pose_cmd[...] = cart_pos
        self._stiffness[...] = cart_stiffness
        self._damping[...] = cart_damping
        self._wrench[...] = add_tcp_ft

    @property
    def torques(self) -> np.ndarray:
        """The last step's torques: the controller's own buffer (what ``compute`` returns)."""
        return self._tau

    def step_at(self, q_at: int, qd_at: int, has_force: bool, hold: bool, has_command: bool) -> None:
        """``compute`` from buffers by address: the state at ``q_at``, ``qd_at``; the force
        and the command already in ``_force``, ``_pose_cmd``, ``_stiffness``, ``_damping``,
        ``_wrench``.  The torques go to ``_tau``."""
        state, table, limit, at = self.state_at, self.table_at, self.config.cartesian_force_limit, self._at
        if _law_cycle is not None:
            done = _law_cycle(state, table, q_at, qd_at, at["force"], has_force, limit, hold, has_command,
                              COMPUTE_ALL_TERMS, self._model_at, self._data_at)
            if done == LAW_DYNAMICS_FAILED:
                raise RuntimeError("Pinocchio's computeAllTerms failed in the KRC's step")
            if done == LAW_JOINT_IMPEDANCE:
                self._joint_impedance()
                _law_end(state, table)
            return
        # without the extension's C functions: the dynamics through Python, between the kernels
        if not _law_begin(state, table, q_at, qd_at, at["force"], has_force, limit):
            return
        self.kin.update_dynamics(self._q, self._qd)
        if _law_torques(state, table, hold, has_command):
            self._joint_impedance()
        _law_end(state, table)

    # ------------------------------------------------------------------ laws

    def _joint_impedance(self):
        # not a kernel: JNT_IMP serves remotes over FRI (etar-bench serve), not the
        # allocation-free reproduction loop
        s = self._state
        s[_INTERPOLATING] = s[_HAS_TARGET] = 0  # a later hold holds where it then is
        M = self.kin.views["M"]
        damping = 2.0 * self._jnt_d * np.sqrt(self._jnt_k * np.diag(M))
        self._tau[...] = (self._jnt_k * (self._jnt_cmd - self._q) - damping * self._qd + self._jnt_trq
                          + self.kin.views["nle"])
        self.last_wrench_tcp.fill(0.0)

    @property
    def reached_target(self) -> bool:
        """POSITION mode: the interpolated target has arrived at the final target."""
        return (bool(self._state[_HAS_TARGET] and self._state[_INTERPOLATING])
                and np.allclose(self._q_interp, self._q_target, atol=1e-9))


def first_command_jump(krc: KrcController, cmd: CommandPacket, m: MeasurementPacket | None) -> str:
    """Why the first command of a command-mode session jumps too far from the measured
    state ``m`` to be applied ('' if it does not): its pose (CART_IMP) or its joints."""
    if m is None:
        return ""
    limits = krc.config
    if krc.mode == ControlMode.CART_IMP:
        cmd_pose, msr = np.asarray(cmd.cart_pos).reshape(3, 4), np.asarray(m.msr_cart_pos).reshape(3, 4)
        dist = float(np.linalg.norm(cmd_pose[:, 3] - msr[:, 3]))
        angle = float(np.linalg.norm(pin.log3(msr[:, :3].T @ cmd_pose[:, :3])))
        if dist > limits.first_command_max_jump_m or angle > limits.first_command_max_jump_rad:
            return (f"first command {dist * 1e3:.1f} mm and {np.rad2deg(angle):.1f} deg from the measured pose "
                    f"(limits {limits.first_command_max_jump_m * 1e3:.0f} mm, "
                    f"{np.rad2deg(limits.first_command_max_jump_rad):.1f} deg)")
    elif cmd.jnt_pos is not None:
        step = np.abs(np.asarray(cmd.jnt_pos) - m.msr_jnt_pos)
        j = int(np.argmax(step))
        if step[j] > limits.first_command_max_jump_rad:
            return (f"first command's joint {j + 1} {np.rad2deg(step[j]):.1f} deg from the measured one "
                    f"(limit {np.rad2deg(limits.first_command_max_jump_rad):.1f} deg)")
    return ""


def measurement_extras(kin: ArmKinematics, data, q_msr: np.ndarray, krc: KrcController, link, tau_ext: np.ndarray,
                       cycle_ns: int) -> MeasurementExtras:
    """What an FRI 1.0 measurement datagram carries beyond the packet, from the one kinematic
    model at the measured joint positions ``q_msr`` (Pinocchio's ``data`` a scratch of the
    caller's): the Jacobian in the tcp frame (the frame of ``estExtTcpFT``, KUKA's row order),
    the joint-space inertia, the gravity torques, the estimated external joint torques
    ``tau_ext``, the drives' torques of the last cycle as ``msrJntTrq`` (the joint torque
    sensors' reading, friction aside), and the commanded poses: in command mode the last
    command the FRI ``link`` applied, in monitor mode the measured ones (what a KRC holding
    its pose reports)."""
    model, tcp = kin.model, kin.frame_ids["tcp"]
    pin.computeFrameJacobian(model, data, q_msr, tcp, pin.ReferenceFrame.LOCAL)
    jacobian = pin.getFrameJacobian(model, data, tcp, pin.ReferenceFrame.LOCAL)
    mass = pin.crba(model, data, q_msr)
    mass = np.triu(mass) + np.triu(mass, 1).T
    gravity = pin.computeGeneralizedGravity(model, data, q_msr)
    applied = link.last_applied
    cmd_cart = cmd_jnt = None
    if applied is not None:
        cmd_cart = np.array(applied.cart_pos)
        if applied.jnt_pos is not None and krc.mode != ControlMode.CART_IMP:
            cmd_jnt = np.array(applied.jnt_pos)
    return MeasurementExtras(
        cmd_jnt_pos=cmd_jnt, cmd_cart_pos=cmd_cart if krc.mode == ControlMode.CART_IMP else None,
        msr_jnt_trq=krc.last_tau.copy(), est_ext_jnt_trq=tau_ext.copy(), jacobian=fri_order(jacobian),
        mass_matrix=mass, gravity=gravity.copy(), miss_counter=link.statistics().missed, error=int(krc.safety),
        sample_time_s=cycle_ns * 1e-9)
