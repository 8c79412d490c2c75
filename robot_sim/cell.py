"""One simulated work cell: the LWR4+ behind its KRC/FRI link, the ATI sensor, a world.

A cycle is one FRI cycle (1 ms) and one physics step, in the fixed order

    m = cell.begin_cycle()            # KRC measures and sends (FRI measurement packet)
    cell.receive(command, t_arrival)  # the remote's answer, if any (any number of calls)
    out = cell.end_cycle(hand)        # KRC closes the cycle, applies the command,
                                      # physics steps, the F/T sensor samples

so the same cell serves the realtime and lockstep clocks: only who supplies the
answers, and when, differs.  Time is the integer cycle count times the cycle.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from numba import njit

from kernel_plumbing import blas
from kernel_plumbing.addresses import (JIT, HoldsAddresses, address, addresses, carray_at, copy_at, entry,
                                       int64_address, int64_array_at)
from robot_sim.arm.kinematics import (COMPUTE_ALL_TERMS, MEASURED_KINEMATICS, READY, ArmKinematics,
                                      call_measured_kinematics)
from robot_sim.ati.rdt import RdtRecord
from robot_sim.ati.sensor import AtiConfig, AtiSensor
from robot_sim.krc.faults import LinkFaults
from robot_sim.krc.link import ClosedCycle, CycleOutcome, FriConfig, FriLink
from robot_sim.krc.packets import (FRI_AXIS_ORDER, CommandPacket, ControlMode, FriState, MeasurementExtras,
                                   MeasurementPacket, fri_order)
from robot_sim.krc.law import (LAW_DONE, ImpedanceCommand, KrcConfig, KrcController, first_command_jump, law_cycle_at,
                               measurement_extras)
from robot_sim.krc.law_arithmetic import pose_at
from robot_sim.world.physics import MJ_STEP, PhysicsError, Simulation, step_at
from robot_sim.world.tasks import TIMESTEP, WorldSpec

# Noise of the measured joint positions FRI reports (rad, per joint, white).
# Not from a KUKA datasheet (none gives it): chosen so the reported tcp position
# scatters by about 20 um per axis at the valley postures, below the LWR4+'s
# +-0.05 mm repeatability.  It matters to learning: noise-free positions let the
# auto-regression resolve sub-micrometre structure (the hand's lag after each
# turn, its speed wander) that no lab recording shows, and BIC then pays for
# extra phases to model it.
JOINT_POSITION_NOISE = 2.5e-5


_NOISE_BLOCK = 1000
_REGULARISATION = 1e-9 * np.eye(6)
try:
    # np.linalg.solve's own kernel without its Python wrapper (8 of its 11 us here): the
    # matrix is J J^T + 1e-9 I, positive definite, so the singular-matrix check is moot
    from numpy.linalg._umath_linalg import solve1 as _solve1

    def _solve(a, b):
        return _solve1(a, b, signature="dd->d")
except ImportError:  # a numpy without it: the public function, same result
    _solve = np.linalg.solve


def _external_wrench_numpy(J, tau, JJt, Jtau):
    """The estimate F = (J J^T + 1e-9 I)^-1 J tau through numpy (the reference)."""
    np.matmul(J, J.T, out=JJt)
    JJt += _REGULARISATION
    np.matmul(J, tau, out=Jtau)
    return _solve(JJt, Jtau)


@njit(**JIT)
def _external_wrench_at(syrk, gemv, gesv, j, tau, reg, jjt, jtau, lu, ints, ipiv, out):
    """``_external_wrench_numpy`` in one call, through the functions numpy calls
    (kernel_plumbing.blas): J J^T by dsyrk (numpy's matmul of an array with its own transpose),
    mirrored; J tau by dgemv; the solve by dgesv on a column-major copy, as numpy's solve
    does.  ``ints``: int64 [n, nrhs, lda, ldb, info]; returns LAPACK's info."""
    row, upper, no_trans = np.int32(blas.ROW_MAJOR), np.int32(blas.UPPER), np.int32(blas.NO_TRANS)
    blas.call_syrk(syrk, row, upper, no_trans, 6, 7, 1.0, j, 7, 0.0, jjt, 6)
    a, r, f = carray_at(jjt, (6, 6)), carray_at(reg, (6, 6)), carray_at(lu, (6, 6))
    for i in range(6):
        for k in range(i):
            a[i, k] = a[k, i]
    for i in range(6):
        for k in range(6):
            a[i, k] += r[i, k]
            f[k, i] = a[i, k]
    blas.call_gemv(gemv, row, no_trans, 6, 7, 1.0, j, 7, tau, 1, 0.0, jtau, 1)
    b, x = carray_at(jtau, (6,)), carray_at(out, (6,))
    for i in range(6):
        x[i] = b[i]
    blas.call_gesv(gesv, ints, ints + 8, lu, ints + 16, ipiv, out, ints + 24, ints + 32)
    return blas.int64_at(ints + 32)


def _external_wrench_kernel():
    """(the compiled estimate, '') or (None, why not): where numpy's library was not found,
    the kernel would not compile, or random Jacobians and torques of the cycle's shapes give
    any other bit than the numpy path (checked once, at import)."""
    if not blas.AVAILABLE:
        return None, blas.WHY
    try:
        kernel = entry(_external_wrench_at, addresses(12))
    except Exception as e:  # noqa: BLE001 - the numpy path records the same numbers
        return None, f"the kernel did not compile: {e}"
    rng = np.random.default_rng(27)
    JJt, Jtau, scratch = np.empty((6, 6)), np.empty(6), ExternalWrenchScratch()
    for k in range(64):
        scratch.jacobian[:], scratch.tau[:] = rng.standard_normal((6, 7)), rng.standard_normal(7)
        if not np.array_equal(scratch.solve(kernel), _external_wrench_numpy(scratch.jacobian, scratch.tau, JJt, Jtau)):
            return None, f"its result differs from numpy's for random input {k}"
    return kernel, ""


class ExternalWrenchScratch(HoldsAddresses):
    """The compiled estimate's inputs and outputs, preallocated and passed by address:
    ``jacobian`` (6, 7) and ``tau`` (7,) in, ``out`` (6,) the estimate."""

    def __init__(self, tau: np.ndarray | None = None):
        self.jacobian = np.empty((6, 7))
        self.tau = np.empty(7) if tau is None else tau
        self.jjt, self.jtau, self.lu, self.out = np.empty((6, 6)), np.empty(6), np.empty((6, 6)), np.empty(6)
        self.ints = np.array([6, 1, 6, 6, 0], dtype=np.int64)
        self.ipiv = np.zeros(6, dtype=np.int64)
        self.args = (blas.SYRK, blas.GEMV, blas.GESV, address(self.jacobian), address(self.tau),
                     address(_REGULARISATION), address(self.jjt), address(self.jtau), address(self.lu),
                     self.ints.ctypes.data, self.ipiv.ctypes.data, address(self.out))

    def solve(self, kernel) -> np.ndarray:
        """The estimate for ``jacobian`` and ``tau`` as they are now, into ``out``."""
        if kernel(*self.args):
            self.out.fill(np.nan)  # a singular system: NaN, as numpy's solve kernel (_solve) gives
        return self.out


_EXTERNAL_WRENCH, EXTERNAL_WRENCH_WHY = _external_wrench_kernel()


@njit(**JIT)
def _physics_cycle_at(steps, law_state_at, law_table_at, q_at, qd_at, arm_qpos_at, arm_qvel_at, force_at, has_force,
                      force_limit, hold, has_command, dynamics_fn, model_at, data_at, sim_table_at, nv, arm_dof, hand,
                      step_fn, tau_at, sim_tau_at):
    """The physics of one FRI cycle in one call: ``steps`` times the measured joint state,
    the KRC's law (robot_sim.krc.law.law_cycle_at, Pinocchio through ``dynamics_fn``) into
    ``tau_at``, the torques and the hand applied and MuJoCo stepped
    (robot_sim.world.physics.step_at through ``step_fn``): ``RobotCell.end_cycle``'s loop.
    Returns the steps done; fewer than ``steps``: the law (Pinocchio) or the step failed at
    the next one (-1 - steps done: the step diverged)."""
    for step in range(steps):
        copy_at(arm_qpos_at, q_at, 7)
        copy_at(arm_qvel_at, qd_at, 7)
        if law_cycle_at(law_state_at, law_table_at, q_at, qd_at, force_at, has_force, force_limit, hold, has_command,
                        dynamics_fn, model_at, data_at) != LAW_DONE:
            return step
        copy_at(tau_at, sim_tau_at, 7)
        if not step_at(sim_table_at, nv, arm_dof, hand, step_fn):
            return -1 - step
    return steps


# The buffers the measurement kernel reaches (``RobotCell._measure_table``), by index
MEASURE_BUFFERS = ("arm_qpos", "arm_qvel", "q", "qd", "noise", "q_msr", "true_jacobian", "rotation", "translation",
                   "true_pose", "local", "true_twist", "wrench_jacobian", "wrench", "cart", "wrench_fri")
(_ARM_QPOS, _ARM_QVEL, _QT, _QDT, _NOISE, _Q_MSR, _TRUE_JACOBIAN, _ROTATION, _TRANSLATION, _TRUE_POSE, _LOCAL,
 _TRUE_TWIST, _WRENCH_JACOBIAN, _WRENCH, _CART, _WRENCH_FRI) = range(len(MEASURE_BUFFERS))


@njit(**JIT)
def _measure_at(table_at, joint_noise, kinematics_fn, model_at, data_at, frame, gemv, wrench_args_at):
    """What ``RobotCell.begin_cycle`` measures before the FRI link, in one call: the true
    joint state read from MuJoCo; the measured joints (the true ones plus this cycle's row
    of noise); the tcp's true pose and twist (Pinocchio at the true joints, the twist
    through the dgemv numpy's matmul calls, so the same bits); then Pinocchio at the
    measured joints, the external wrench estimate (``_external_wrench_at``, its arguments
    in the int64 table at ``wrench_args_at``; also in FRI's order) and the measured tcp pose.
    Returns False if Pinocchio failed."""
    at = int64_array_at(table_at, len(MEASURE_BUFFERS))
    copy_at(at[_ARM_QPOS], at[_QT], 7)
    copy_at(at[_ARM_QVEL], at[_QDT], 7)
    q, noise, q_msr = carray_at(at[_QT], (7,)), carray_at(at[_NOISE], (7,)), carray_at(at[_Q_MSR], (7,))
    for i in range(7):
        q_msr[i] = noise[i] * joint_noise
        q_msr[i] += q[i]
    if call_measured_kinematics(kinematics_fn, model_at, data_at, at[_QT], frame, at[_TRUE_JACOBIAN]) != 0:
        return False
    pose_at(at[_ROTATION], at[_TRANSLATION], at[_TRUE_POSE])
    row, no_trans, trans = np.int32(blas.ROW_MAJOR), np.int32(blas.NO_TRANS), np.int32(blas.TRANS)
    # local = J qd, [v; w] in tcp axes (J C-contiguous), then R v and R w (R column-major,
    # as a transposed row-major matrix): the calls numpy's matmul makes for each
    blas.call_gemv(gemv, row, no_trans, 6, 7, 1.0, at[_TRUE_JACOBIAN], 7, at[_QDT], 1, 0.0, at[_LOCAL], 1)
    blas.call_gemv(gemv, row, trans, 3, 3, 1.0, at[_ROTATION], 3, at[_LOCAL], 1, 0.0, at[_TRUE_TWIST], 1)
    blas.call_gemv(gemv, row, trans, 3, 3, 1.0, at[_ROTATION], 3, at[_LOCAL] + 24, 1, 0.0, at[_TRUE_TWIST] + 24, 1)
    if call_measured_kinematics(kinematics_fn, model_at, data_at, at[_Q_MSR], frame, at[_WRENCH_JACOBIAN]) != 0:
        return False
    w = int64_array_at(wrench_args_at, 12)
    wrench, fri = carray_at(at[_WRENCH], (6,)), carray_at(at[_WRENCH_FRI], (6,))
    if _external_wrench_at(w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7], w[8], w[9], w[10], w[11]):
        wrench[:] = np.nan  # a singular system: NaN, as numpy's solve kernel gives
    for i in range(6):
        fri[i] = wrench[FRI_AXIS_ORDER[i]]  # FRI orders the torques Tz, Ty, Tx
    pose_at(at[_ROTATION], at[_TRANSLATION], at[_CART])
    return True


_MEASURE = entry(_measure_at, f"int64, float64, {addresses(6)}") \
    if MEASURED_KINEMATICS and _EXTERNAL_WRENCH is not None else None


_PHYSICS_CYCLE = entry(_physics_cycle_at, f"int64, {addresses(7)}, boolean, float64, boolean, boolean, "
                                          f"{addresses(6)}, boolean, {addresses(3)}") \
    if MJ_STEP and COMPUTE_ALL_TERMS else None


@dataclass
class CycleResult:
    outcome: CycleOutcome
    ft: RdtRecord | None  # the ATI record sampled at the end of the cycle (None: a cell without sensor)
    contact_force: np.ndarray  # (3,) true environment force on the tip, world axes
    touching: list  # geom names the tip touches
    tau: np.ndarray  # (7,) joint torques applied
    t_ns: int  # simulation time after the step


class CompiledCycle(HoldsAddresses):
    """A cell's cycle through its two kernels, ``_measure_at`` and ``_physics_cycle_at``:
    the addresses they take, gathered once (the tcp's views of Pinocchio's data among
    them), and their calls.  The same numbers as the cell's Python calls."""

    def __init__(self, cell: "RobotCell"):
        self.cell = cell
        rotation, translation = cell.kin.frame_views("tcp")
        scratch = cell._wrench_scratch
        buffers = dict(arm_qpos=cell.sim.arm_qpos_at, arm_qvel=cell.sim.arm_qvel_at, q=cell._q_at, qd=cell._qd_at,
                       noise=0, q_msr=address(cell._q_msr), true_jacobian=address(cell._true_jacobian),
                       rotation=address(rotation), translation=address(translation),
                       true_pose=address(cell._true_pose), local=address(cell._local_twist),
                       true_twist=address(cell._true_twist), wrench_jacobian=address(scratch.jacobian),
                       wrench=address(scratch.out), cart=address(cell._cart_pos),
                       wrench_fri=address(cell._est_ext_tcp_ft))
        self._table = np.array([buffers[name] for name in MEASURE_BUFFERS], dtype=np.int64)
        self._table_at = int64_address(self._table)
        self._wrench_args = np.array(scratch.args, dtype=np.int64)
        self._wrench_args_at = int64_address(self._wrench_args)
        (self._model_at, self._data_at), self._tcp_frame = cell.kin.native, cell.kin.frame_ids["tcp"]

    def measure(self, noise_row_at: int) -> None:
        """``begin_cycle``'s measurement, the joint noise's row at ``noise_row_at``."""
        self._table[_NOISE] = noise_row_at
        if not _MEASURE(self._table_at, self.cell.joint_noise, MEASURED_KINEMATICS, self._model_at, self._data_at,
                        self._tcp_frame, blas.GEMV, self._wrench_args_at):
            raise RuntimeError("Pinocchio's kinematics failed in the KRC's measurement")

    def physics(self, impedance, force_estimate, hand_wrench) -> None:
        """The loop of ``end_cycle``: the same law, the same steps, the same numbers."""
        self.cell.krc.load(impedance, force_estimate)
        self.step(impedance is not None, force_estimate is not None, hand_wrench)

    def step(self, has_command: bool, has_force: bool, hand_wrench) -> None:
        """``physics`` with the command and the force already in the KRC's buffers."""
        cell = self.cell
        krc, sim = cell.krc, cell.sim
        hand = hand_wrench is not None
        if hand:
            sim.load_hand(hand_wrench)
        steps = cell.steps_per_cycle
        done = _PHYSICS_CYCLE(steps, krc.state_at, krc.table_at, cell._q_at, cell._qd_at, sim.arm_qpos_at,
                              sim.arm_qvel_at, krc.force_at, has_force, krc.config.cartesian_force_limit,
                              not has_command, has_command, COMPUTE_ALL_TERMS, self._model_at, self._data_at,
                              sim.table_at, sim.nv, sim.arm_dof, hand, MJ_STEP, krc.tau_at, sim.tau_at)
        if done < 0:
            raise PhysicsError(f"simulation diverged at t={sim.time:.3f} s (bad acceleration)")
        if done < steps:
            raise RuntimeError("Pinocchio's computeAllTerms failed in the KRC's step")


class RobotCell(HoldsAddresses):
    def __init__(self, world: WorldSpec, *, seed: int = 0, fri_config: FriConfig | None = None,
                 ati_config: AtiConfig | None = None, krc_config: KrcConfig | None = None,
                 faults: LinkFaults | None = None, joint_noise: float = JOINT_POSITION_NOISE,
                 with_sensor: bool = True):
        self.world = world
        self.sim = Simulation(world)
        self.kin = ArmKinematics()
        step_ns = round(TIMESTEP * 1e9) // self.sim.substeps
        # the KRC's law runs every physics step: its rate limits count in steps
        krc_config = krc_config or KrcConfig()
        self.krc = KrcController(self.kin, dataclasses.replace(krc_config, cycle_s=step_ns / 1e9)
                                 if self.sim.substeps > 1 else krc_config)
        self.fri = FriLink(fri_config, faults)
        if self.fri.config.cycle_ns % step_ns or self.fri.config.cycle_ns < step_ns:
            raise ValueError(f"FRI cycle {self.fri.config.cycle_ns} ns must be a whole number of physics steps "
                             f"({step_ns} ns)")
        # friOpen(ms) with more than 1 ms, or a world stepped finer than the cycle (the
        # reference physics): the KRC's own control still runs every physics step, with
        # the cycle's command; FRI measures and takes commands every cycle
        self.steps_per_cycle = self.fri.config.cycle_ns // step_ns
        self.ati_config = ati_config or AtiConfig.mini45()
        # without_sensor: whoever runs the cell samples the tool wrench with its own
        # sensor model (the ft_sensor node); end_cycle's ``ft`` is then None
        self.ati = AtiSensor(self.ati_config, seed) if with_sensor else None
        self.cycle_ns = self.fri.config.cycle_ns
        self.cycle = 0
        self._q = np.zeros(7)
        self._qd = np.zeros(7)
        if not (np.isfinite(joint_noise) and joint_noise >= 0.0):
            raise ValueError(f"joint_noise must be a standard deviation >= 0 rad, got {joint_noise!r}")
        self.joint_noise = float(joint_noise)
        self._q_at, self._qd_at = address(self._q), address(self._qd)
        self._q_msr = np.zeros(7)
        self._joint_rng = np.random.default_rng([seed, 1])  # its own stream: the ATI's draws stay as they were
        self._tau_ext = np.zeros(7)
        self._JJt = np.empty((6, 6))
        self._Jtau = np.empty(6)
        self._cart_pos = np.empty((3, 4))  # FRI's 3x4 row-major [R | p], filled from views of the kinematics
        self._est_ext_tcp_ft = np.empty(6)  # the wrench estimate in FRI's order
        self._true_jacobian = np.empty((6, 7))
        self._true_pose = np.zeros((3, 4))
        self._true_twist = np.zeros(6)
        self._local_twist = np.zeros(6)
        self._joint_noise_block = np.empty((0, 7))
        self._joint_noise_i = 0
        self._true_wrench = np.zeros(6)
        self._true_wrench_at, self._tau_ext_at = address(self._true_wrench), address(self._tau_ext)
        self._wrench_scratch = ExternalWrenchScratch(self._tau_ext)  # the measurement's estimate
        self._probe_scratch = None  # external_wrench_tcp's
        self._measured = False  # a cycle has been measured: the KRC's law has a force estimate
        self._noise_block_at = 0
        self._last_measurement: MeasurementPacket | None = None
        self._extras_data = None  # Pinocchio data of its own for fri_extras
        # the KRC's checks on a lab's remote (FRI over UDP): its first command in command mode
        # must continue from the measured state (one that jumps is refused, the reason kept
        # here until read), and a safety stop drops the link to monitor mode
        self.remote_checks = False
        self.first_command_refused = ""
        self._first_commands = 0  # of this command-mode session, still to check
        self._compiled = CompiledCycle(self) if _MEASURE is not None and _PHYSICS_CYCLE is not None else None
        self.place(READY)

    @property
    def t_ns(self) -> int:
        return self.cycle * self.cycle_ns

    # ------------------------------------------------------------- set-up

    def place(self, q: np.ndarray) -> None:
        """Put the arm at joint positions q, at rest (between runs: the lab
        would drive it there in POSITION mode)."""
        self.sim.reset(np.asarray(q, dtype=np.float64))
        self._sense()
        self.krc.reset_safety()

    def place_tcp(self, position, rotation, seed_q=READY) -> np.ndarray:
        q = self.kin.inverse_kinematics(pin.SE3(np.asarray(rotation, float), np.asarray(position, float)), seed_q)
        self.place(q)
        return q

    def start(self) -> None:
        """Open the FRI link (OFF -> MON)."""
        self.fri.start(self.t_ns)

    # --------------------------------------------------------------- cycle

    def begin_cycle(self) -> MeasurementPacket:
        self._measure_numbers()
        m = self.fri.measurement(self.t_ns, *self.measured_views())
        self._last_measurement = m
        return m

    def measure(self) -> int:
        """``begin_cycle`` without its packet (made only for a lab remote's checks, which judge
        its first command against it): the seq; the numbers are ``measured_views``', the rest
        of the packet ``FriLink.sent_header``'s."""
        if self.remote_checks:
            return self.begin_cycle().seq
        self._measure_numbers()
        self._last_measurement = None
        return self.fri.open_cycle(self.t_ns)

    def _measure_numbers(self) -> None:
        """What the KRC measures, into the cell's buffers (``measured_views``, the tcp's true motion)."""
        sim, kin = self.sim, self.kin
        if self._compiled is None:
            sim.joint_positions(self._q)
            sim.joint_velocities(self._qd)
        # the KRC reports measured joint positions, and the tcp pose from them; the
        # noise is drawn a block at a time (the same numbers as 7 per cycle)
        i = self._joint_noise_i
        if i >= len(self._joint_noise_block):
            self._joint_noise_block = self._joint_rng.standard_normal((_NOISE_BLOCK, 7))
            self._noise_block_at = address(self._joint_noise_block)
            i = 0
        self._joint_noise_i = i + 1
        self._measured = True
        if self._compiled is not None:
            return self._compiled.measure(self._noise_block_at + i * 56)  # this cycle's row of 7 float64
        np.multiply(self._joint_noise_block[i], self.joint_noise, out=self._q_msr)
        self._q_msr += self._q
        self._true_motion()
        if _EXTERNAL_WRENCH is not None:
            kin.update_with_jacobian(self._q_msr, "tcp", self._wrench_scratch.jacobian)
            self._wrench_scratch.solve(_EXTERNAL_WRENCH)
        else:
            kin.update(self._q_msr)
            self._wrench_scratch.out[:] = _external_wrench_numpy(kin.jacobian("tcp", pin.ReferenceFrame.LOCAL),
                                                                 self._tau_ext, self._JJt, self._Jtau)
        np.take(self._wrench_scratch.out, FRI_AXIS_ORDER, out=self._est_ext_tcp_ft)
        R, p = kin.frame_views("tcp")
        self._cart_pos[:, :3] = R
        self._cart_pos[:, 3] = p

    def measured_views(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The open cycle's measured joint positions (7,), tcp pose (12,) and external wrench (6,)
        as FRI's packet has them (torques Tz Ty Tx): the cell's own buffers, to copy at once."""
        return self._q_msr, self._cart_pos.reshape(12), self._est_ext_tcp_ft

    def _true_motion(self) -> None:
        """The tcp's true pose and velocity at the cycle's start, from the true joint state
        (what a hand holding the tool feels), before the measured kinematics: the model's
        data is left holding the measurement, as before."""
        kin, jacobian = self.kin, self._true_jacobian
        kin.update_with_jacobian(self._q, "tcp", jacobian)
        R, p = kin.frame_views("tcp")
        pose = self._true_pose
        pose[:, :3] = R
        pose[:, 3] = p
        local = jacobian @ self._qd  # [v; w] in tcp axes
        twist = self._true_twist
        twist[:3] = R @ local[:3]
        twist[3:] = R @ local[3:]

    @property
    def true_tcp_pose(self) -> np.ndarray:
        """(12,) the tcp's true pose at the open cycle's start, 3x4 row-major [R | p], base frame."""
        return self._true_pose.reshape(12).copy()

    @property
    def true_tcp_twist(self) -> np.ndarray:
        """(6,) the tcp's true velocity at the open cycle's start [v; w], base frame axes."""
        return self._true_twist.copy()

    def external_wrench_tcp(self) -> np.ndarray:
        """The KRC's estimate of the external wrench at the tcp, tcp axes, [F; T] (from joint torques:
        F = (J^T)^+ tau_ext, the torques read with the rest of the state after the last step), from
        the kinematics as they are now; a copy, made in buffers of its own (not the measurement's)."""
        kin = self.kin
        # least squares J^T F = tau through the normal equations: J has full row
        # rank away from singularities, and this is 6x cheaper than lstsq
        if _EXTERNAL_WRENCH is None:
            return _external_wrench_numpy(kin.jacobian("tcp", pin.ReferenceFrame.LOCAL), self._tau_ext,
                                          self._JJt, self._Jtau).copy()
        scratch = self._probe_scratch = self._probe_scratch or ExternalWrenchScratch(self._tau_ext)
        np.copyto(scratch.jacobian, pin.getFrameJacobian(kin.model, kin.data, kin.frame_ids["tcp"],
                                                         pin.ReferenceFrame.LOCAL))
        return scratch.solve(_EXTERNAL_WRENCH).copy()

    def fri_extras(self) -> MeasurementExtras:
        """What an FRI 1.0 measurement datagram carries beyond the packet, for the cycle just opened
        (call after ``begin_cycle``): ``robot_sim.krc.law.measurement_extras`` at the measured joint
        positions, with a Pinocchio data of its own.  Allocates: for the UDP endpoint."""
        if self._extras_data is None:
            self._extras_data = self.kin.model.createData()
        return measurement_extras(self.kin, self._extras_data, self._q_msr, self.krc, self.fri, self._tau_ext,
                                  self.cycle_ns)

    def receive(self, command: CommandPacket, t_arrival_ns: int) -> bool:
        return self.fri.receive(command, t_arrival_ns)

    def deliver(self, command: CommandPacket, t_sent_ns: int, *, owned: bool = False) -> bool:
        """A command sent at ``t_sent_ns`` through the link's fault model (loss, delay, corruption;
        ``faults``), then received; without faults the same as ``receive`` (``owned``: see ``FriLink.receive``)."""
        return self.fri.deliver(command, t_sent_ns, owned=owned)

    def end_cycle(self, hand_wrench: np.ndarray | None = None) -> CycleResult:
        before = self.fri.last_applied
        outcome = self.fri.end_cycle(self.t_ns + self.cycle_ns)
        cmd = outcome.command
        if cmd is not None and before is None:
            # a command-mode session begins: the answer to the last monitor-mode measurement
            # and the remote's first answer to one that says CMD are its first commands
            self._first_commands = 2
        if self.remote_checks and cmd is not None and self._first_commands and not outcome.bridged:
            self._first_commands -= 1
            jump = first_command_jump(self.krc, cmd, self._last_measurement)
            if jump:
                # as a KRC does with a first command far from where the arm is: not applied,
                # back to monitor mode, the arm held
                self.first_command_refused = jump
                self.fri.request_monitor_mode()
                cmd = None
        impedance = None
        if cmd is not None and not outcome.hold:
            mode = self.krc.mode
            if mode == ControlMode.POSITION and cmd.jnt_pos is not None:
                self.krc.set_joint_target(cmd.jnt_pos, streamed=True)  # a remote streams it every cycle
            elif mode == ControlMode.JNT_IMP and cmd.jnt_pos is not None:
                self.krc.set_joint_impedance(cmd.jnt_pos, cmd.jnt_stiffness, cmd.jnt_damping, cmd.add_jnt_trq)
            impedance = ImpedanceCommand(cmd.cart_pos, cmd.cart_stiffness, cmd.cart_damping,
                                         fri_order(cmd.add_tcp_ft))
        force_estimate = self._wrench_scratch.out[:3].copy() if self._measured else None
        if self._compiled is not None and not self.remote_checks and self.krc.mode != ControlMode.JNT_IMP:
            self._compiled.physics(impedance, force_estimate, hand_wrench)
        else:
            for step in range(self.steps_per_cycle):
                if step:
                    self.sim.joint_positions(self._q)
                    self.sim.joint_velocities(self._qd)
                tau = self.krc.compute(self._q, self._qd, impedance, hold=impedance is None,
                                       external_force=force_estimate)
                if self.remote_checks and self.krc.safety and self.fri.state == FriState.CMD:
                    self.fri.request_monitor_mode()  # the arm is held where it stopped: the remote is told so
                self.sim.apply(tau, hand_wrench)
                self.sim.step()
        tau = self.krc.torques
        self.cycle += 1
        self._sense()
        record = self.ati.read(self._true_wrench, self.t_ns) if self.ati is not None else None
        return CycleResult(outcome, record, self._contact_force.copy(), list(self._touching), tau.copy(), self.t_ns)

    def close(self, hand_wrench: np.ndarray | None = None) -> ClosedCycle:
        """``end_cycle`` for a caller that needs only how the cycle closed (the robot node): the
        same cycle; compiled in CART_IMP without a remote's checks, the KRC loads the command
        from the FRI link's slot and nothing is copied out of the cell."""
        fri, krc, before = self.fri, self.krc, self.fri.has_last_applied
        if self._compiled is None or self.remote_checks or self.ati is not None or krc.mode != ControlMode.CART_IMP:
            return self.end_cycle(hand_wrench).outcome
        closed = fri.close(self.t_ns + self.cycle_ns)
        if not closed.hold:
            if not before:
                self._first_commands = 2  # a command-mode session begins (end_cycle)
            krc.load_applied(fri.applied_numbers_at)
        if self._measured:
            krc.load(None, self._wrench_scratch.out[:3])
        self._compiled.step(not closed.hold, self._measured, hand_wrench)
        self.cycle += 1
        self._sense()
        return closed

    def _sense(self) -> None:
        """The physics' truth of the current state, read once per step: the tool wrench on the
        sensor, the external joint torques, the contact force on the tip, what it touches."""
        self.sim.sense_at(self._true_wrench_at, self._tau_ext_at)
        self._contact_force, self._touching = self.sim.tip_contacts()

    @property
    def tool_wrench(self) -> np.ndarray:
        """(6,) what the tool transmits to the F/T sensor now, sensor frame."""
        return self._true_wrench.copy()

    @property
    def contact_force(self) -> np.ndarray:
        """(3,) the environment's force on the tip now, world axes."""
        return self._contact_force.copy()

    @property
    def touching(self) -> list:
        """Names of the geoms the tip touches now."""
        return list(self._touching)

    def truth_views(self) -> tuple[np.ndarray, np.ndarray, list, np.ndarray, np.ndarray]:
        """``tool_wrench``, ``contact_force``, ``touching``, ``true_tcp_pose``, ``true_tcp_twist`` as the cell's
        own buffers, not copies: for a caller that copies them at once (a message's pack) and changes none."""
        return self._true_wrench, self._contact_force, self._touching, self._true_pose.reshape(12), self._true_twist

    # ------------------------------------------------------------ helpers

    def switch_control_mode(self, mode: ControlMode) -> bool:
        """Switch the KRC's control mode (FRI allows it only in MON)."""
        if not self.fri.switch_control_mode(mode):
            return False
        self.krc.switch_mode(mode)
        return True
