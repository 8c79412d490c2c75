"""The FRI 1.0 packets as the KRC judges them: the link's states and qualities, the
control modes, the measurement the KRC sends and the command a remote answers with, and
the checks a command must pass before the KRC will apply it (limits of the LWR4+'s
Cartesian impedance from the FRI 1.0 documentation).  Pure values: no sockets, no clock.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from numba import njit

from kernel_plumbing.addresses import (JIT, HoldsAddresses, address, addresses, carray_at, entry, int64_address,
                                       int64_array_at)
from robot_sim.cycle import FRI_CYCLE_NS

# LWR4+ Cartesian impedance limits from the FRI 1.0 documentation.
MAX_TRANSLATIONAL_STIFFNESS = 5000.0  # N/m
MAX_ROTATIONAL_STIFFNESS = 300.0  # Nm/rad
MAX_JOINT_STIFFNESS = 5000.0  # Nm/rad: an assumption (no document at hand gives the joint limit)
# A commanded pose's rotation must be a rotation: |R R^T - I| and |det R - 1| below
# this.  Loose enough for float32 transport and unnormalised interpolation between
# nearby poses, tight enough to catch zeros, scaling or a reflection.
ROTATION_TOLERANCE = 1e-3

_JNT = 7
_MODE_VALUES = frozenset((0, 1, 2, 3))  # ControlMode values; set lookup is cheaper than ControlMode(x)
_CART = 12
_FT = 6
ALL_DRIVES_POWERED = 0x7F  # robot.power: one bit per drive, 7 joints

# FRI orders rotations (torques, Cartesian stiffness and damping, the Jacobian's rows)
# about z, y, x (A, B, C); the physics and the law use x, y, z.
FRI_AXIS_ORDER = np.array([0, 1, 2, 5, 4, 3])


def fri_order(values) -> np.ndarray:
    """x, y, z, rx, ry, rz <-> FRI's x, y, z, A (about z), B (about y), C (about x), of a
    wrench, a stiffness, a damping or the rows of a (6, 7) Jacobian; the permutation
    is its own inverse."""
    return np.asarray(values, dtype=np.float64)[FRI_AXIS_ORDER]


class FriState(IntEnum):
    OFF = 0
    MON = 1
    CMD = 2


class FriQuality(IntEnum):
    UNACCEPTABLE = 0
    BAD = 1
    OK = 2
    PERFECT = 3


class ControlMode(IntEnum):
    """FRI 1.0 numbering."""

    OTHER = 0
    POSITION = 1
    CART_IMP = 2
    JNT_IMP = 3


@dataclass(slots=True, eq=False)
class MeasurementPacket:
    """What the KRC sends at the start of a cycle.  Arrays are float64 copies.

    The statistics are those of the closed cycles in the window (the current
    cycle is not decided yet).
    """

    seq: int
    reflected_seq: int
    stamp_ns: int
    state: FriState
    quality: FriQuality
    control_mode: ControlMode
    msr_jnt_pos: np.ndarray  # (7,) rad
    msr_cart_pos: np.ndarray  # (12,) 3x4 row-major [R | p], m
    est_ext_tcp_ft: np.ndarray  # (6,) [Fx, Fy, Fz, Tz, Ty, Tx] (FRI 1.0 order)
    answer_rate: float
    latency_s: float
    jitter_s: float
    miss_rate: float


@dataclass(slots=True, eq=False)
class CommandPacket:
    """The remote's answer to measurement ``seq``.

    No checks at construction: a packet decoded from the wire may be garbage and
    must still be representable, so that the KRC can reject and count it.
    ``jnt_pos`` is needed only when ``requested_mode`` is POSITION or JNT_IMP.
    """

    seq: int  # echo of the measurement seq this answers
    cart_pos: np.ndarray  # (12,) 3x4 row-major setpoint
    cart_stiffness: np.ndarray  # (6,) [N/m x3, Nm/rad x3]
    cart_damping: np.ndarray  # (6,) normalised 0..1
    add_tcp_ft: np.ndarray = field(default_factory=lambda: np.zeros(_FT))  # (6,) FRI order like est_ext_tcp_ft
    jnt_pos: np.ndarray | None = None  # (7,) rad
    requested_mode: ControlMode = ControlMode.CART_IMP
    # joint impedance (FRI's jntStiffness, jntDamping, addJntTrq); None: the KRC's own values
    jnt_stiffness: np.ndarray | None = None  # (7,) Nm/rad
    jnt_damping: np.ndarray | None = None  # (7,) normalised 0..1
    add_jnt_trq: np.ndarray | None = None  # (7,) Nm

    @classmethod
    def from_measurement(
        cls,
        m: MeasurementPacket,
        cart_stiffness=None,
        cart_damping=None,
        add_tcp_ft=None,
        requested_mode: ControlMode | None = None,
    ) -> "CommandPacket":
        """An answer to ``m`` whose setpoint is the measured pose.

        Zero stiffness and zero added force (the defaults) is gravity
        compensation (thesis eq. 79), the state kinesthetic teaching is done in.
        Damping defaults to 0.7.
        """
        return cls(
            seq=m.seq,
            cart_pos=np.array(m.msr_cart_pos, dtype=np.float64),
            cart_stiffness=np.zeros(_FT) if cart_stiffness is None else np.array(cart_stiffness, dtype=np.float64),
            cart_damping=np.full(_FT, 0.7) if cart_damping is None else np.array(cart_damping, dtype=np.float64),
            add_tcp_ft=np.zeros(_FT) if add_tcp_ft is None else np.array(add_tcp_ft, dtype=np.float64),
            jnt_pos=np.array(m.msr_jnt_pos, dtype=np.float64),
            requested_mode=m.control_mode if requested_mode is None else ControlMode(requested_mode),
        )

    def is_valid(self) -> tuple[bool, str]:
        """(True, "") or (False, reason naming the offending field).  Never raises."""
        try:
            reason = command_problem(self)
        except Exception as exc:  # garbage of a kind nobody foresaw is still just garbage
            reason = f"unreadable packet ({type(exc).__name__}: {exc})"
        return (reason is None, reason or "")

    def copy(self) -> "CommandPacket":
        """Deep copy with float64 arrays (assumes a valid packet)."""
        return CommandPacket(
            seq=int(self.seq),
            cart_pos=np.array(self.cart_pos, dtype=np.float64),
            cart_stiffness=np.array(self.cart_stiffness, dtype=np.float64),
            cart_damping=np.array(self.cart_damping, dtype=np.float64),
            add_tcp_ft=np.array(self.add_tcp_ft, dtype=np.float64),
            jnt_pos=None if self.jnt_pos is None else np.array(self.jnt_pos, dtype=np.float64),
            requested_mode=ControlMode(self.requested_mode),
            jnt_stiffness=None if self.jnt_stiffness is None else np.array(self.jnt_stiffness, dtype=np.float64),
            jnt_damping=None if self.jnt_damping is None else np.array(self.jnt_damping, dtype=np.float64),
            add_jnt_trq=None if self.add_jnt_trq is None else np.array(self.add_jnt_trq, dtype=np.float64),
        )


# what _numbers_at finds wrong first (0: nothing), the vector and its entry in ``where``
_NOT_FINITE, _TOO_LARGE, _NOT_ORTHONORMAL, _DETERMINANT, _OUT_OF_RANGE = 1, 2, 3, 4, 5
_STIFFNESS_LIMITS = np.array([MAX_TRANSLATIONAL_STIFFNESS] * 3 + [MAX_ROTATIONAL_STIFFNESS] * 3)
# the vectors a command's numbers are checked in, in this order, with their lengths and
# the range of their entries (None: any finite number; the upper end per entry or for all)
_VECTORS = (("cart_pos", _CART, None), ("cart_stiffness", _FT, (0.0, _STIFFNESS_LIMITS)),
            ("cart_damping", _FT, (0.0, 1.0)), ("add_tcp_ft", _FT, None), ("jnt_pos", _JNT, None),
            ("jnt_stiffness", _JNT, (0.0, MAX_JOINT_STIFFNESS)), ("jnt_damping", _JNT, (0.0, 1.0)),
            ("add_jnt_trq", _JNT, None))
_LENGTHS = tuple(n for _, n, _ in _VECTORS)


@njit(**JIT)
def _finite_at(v, which, where):
    """0, or why the float64 vector ``v`` is not finite (its entry in where[1])."""
    total = 0.0
    for x in v:
        total += x
    if math.isfinite(total):  # a finite sum implies finite terms; only then is the entry looked for
        return 0
    where[0] = which
    for i in range(v.shape[0]):
        if not math.isfinite(v[i]):
            where[1] = i
            return _NOT_FINITE
    return _TOO_LARGE


@njit(**JIT)
def _in_range_at(v, low, high, which, where):
    for i in range(v.shape[0]):
        if not low[i] <= v[i] <= high[i]:
            where[0], where[1] = which, i
            return _OUT_OF_RANGE
    return 0


@njit(**JIT)
def _numbers_at(present_at, values_at, lows_at, highs_at, tolerance, where_at, det_at):
    """What is wrong first with a command's numbers (0: nothing): the vectors of _VECTORS in
    the rows of ``values_at`` ((8, _CART), those ``present_at`` marks, int64), each finite,
    the pose's rotation a rotation (its determinant into det_at), each entry of a vector
    with a range within it (``lows_at``, ``highs_at``: per vector, _JNT entries each)."""
    present, values = int64_array_at(present_at, 8), carray_at(values_at, (8, _CART))
    lows, highs = carray_at(lows_at, (8, _JNT)), carray_at(highs_at, (8, _JNT))
    where, det_out = int64_array_at(where_at, 2), carray_at(det_at, (1,))
    for which in range(8):
        if not present[which]:
            continue
        v = values[which, :_LENGTHS[which]]
        problem = _finite_at(v, which, where)
        if problem:
            return problem
        if which == 0:  # rows of R are c[0:3], c[4:7], c[8:11]; c[3], c[7], c[11] the position
            a0, a1, a2, b0, b1, b2, c0, c1, c2 = v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]
            if (abs(a0 * a0 + a1 * a1 + a2 * a2 - 1.0) > tolerance
                    or abs(b0 * b0 + b1 * b1 + b2 * b2 - 1.0) > tolerance
                    or abs(c0 * c0 + c1 * c1 + c2 * c2 - 1.0) > tolerance
                    or abs(a0 * b0 + a1 * b1 + a2 * b2) > tolerance
                    or abs(a0 * c0 + a1 * c1 + a2 * c2) > tolerance
                    or abs(b0 * c0 + b1 * c1 + b2 * c2) > tolerance):
                return _NOT_ORTHONORMAL
            det = a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)
            det_out[0] = det
            if abs(det - 1.0) > tolerance:
                return _DETERMINANT
        elif lows[which, 0] <= highs[which, 0]:  # a vector with a range
            problem = _in_range_at(v, lows[which], highs[which], which, where)
            if problem:
                return problem
    return 0


_NUMBERS = entry(_numbers_at, f"{addresses(4)}, float64, {addresses(2)}")


class CommandChecks(HoldsAddresses):
    """The buffers ``_numbers_at`` reads and writes, made once for every check, and the lock
    that keeps one check at a time in them (the kernel runs without the GIL, and a KRC's
    UDP endpoint checks on its own thread).  ``values`` (8, 12) and ``present`` (8,): a
    command's numbers, where they are checked; an FRI link's are its arriving command's
    slot (robot_sim.krc.link_books), so that a command it accepts is there already."""

    def __init__(self, values: np.ndarray | None = None, present: np.ndarray | None = None):
        self.lock = threading.Lock()
        self.present = np.zeros(8, dtype=np.int64) if present is None else present
        self.values = np.zeros((8, _CART)) if values is None else values
        self.lows, self.highs = np.ones((8, _JNT)), np.zeros((8, _JNT))  # low > high: no range
        for which, (_, n, limits) in enumerate(_VECTORS):
            if limits is not None:
                self.lows[which, :n], self.highs[which, :n] = limits
        self.where = np.zeros(2, dtype=np.int64)
        self.det = np.zeros(1)
        self.args = (int64_address(self.present), address(self.values), address(self.lows), address(self.highs),
                     ROTATION_TOLERANCE, int64_address(self.where), address(self.det))


_CHECKS = CommandChecks()


def _float_vector(value, n: int, name: str) -> tuple[np.ndarray | None, str | None]:
    """``value`` as a numeric vector of n (float64 unless it is an array already), or why it is
    not one."""
    if value is None:
        return None, f"{name} is missing"
    if isinstance(value, np.ndarray):
        if value.shape != (n,):
            return None, f"{name} has shape {value.shape}, expected ({n},)"
        if value.dtype.kind not in "fiu":
            return None, f"{name} has dtype {value.dtype}, expected float"
        return value, None  # copied into float64 for the check
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None, f"{name} is not numeric ({type(value).__name__})"
    if arr.shape != (n,):
        return None, f"{name} has shape {arr.shape}, expected ({n},)"
    return arr, None


def _numbers_problem(originals: list, kept: list, checks: CommandChecks) -> str | None:
    """What ``_numbers_at`` finds wrong with the vectors gathered so far, in words naming
    the field and the value (the original value, as the sender gave it)."""
    present, values = checks.present, checks.values
    with checks.lock:
        for which in range(8):
            vector = kept[which]
            if vector is None:
                present[which] = 0
            else:
                present[which] = 1
                values[which, :len(vector)] = vector
        found = _found(checks)
    return describe(*found, originals, kept, checks)


def _found(checks: CommandChecks) -> tuple[int, float, int, int]:
    """``_numbers_at`` on the numbers in ``checks``' buffers (the caller holds its lock): what
    it found first, the rotation's determinant, the vector and its entry."""
    problem = _NUMBERS(*checks.args)
    return problem, float(checks.det[0]), int(checks.where[0]), int(checks.where[1])


def checked_in_place(checks: CommandChecks, originals) -> str | None:
    """What ``_numbers_at`` finds wrong with the numbers already in ``checks``' buffers (their
    presence flags set), in words as ``command_problem`` gives them; ``originals``: the
    vectors as the sender gave them."""
    with checks.lock:
        if not _NUMBERS(*checks.args):  # the common case: nothing else to read
            return None
        found = _found(checks)
    kept = [checks.values[k, :n] if checks.present[k] else None for k, n in enumerate(_LENGTHS)]
    return describe(*found, originals, kept, checks)


def describe(problem: int, det: float, which: int, i: int, originals: list, kept: list,
             checks: CommandChecks) -> str | None:
    """``_numbers_at``'s finding in words (None: nothing wrong)."""
    if not problem:
        return None
    if problem == _NOT_ORTHONORMAL:
        return "cart_pos rotation is not orthonormal"
    if problem == _DETERMINANT:
        return f"cart_pos rotation has determinant {det:.6g}, expected 1"
    name = _VECTORS[which][0]
    if problem == _TOO_LARGE:
        return f"{name} has values too large to be meaningful"
    original = originals[which]  # an array's own type of number; anything else as the float it was read as
    value = original.tolist()[i] if isinstance(original, np.ndarray) else float(kept[which][i])
    if problem == _NOT_FINITE:
        return f"{name}[{i}] is not finite ({value})"
    if name == "cart_stiffness":
        return f"{name}[{i}] = {value} outside [0, {_STIFFNESS_LIMITS[i]}]"
    if name == "cart_damping":
        return f"{name}[{i}] = {value} outside [0, 1]"
    return f"{name}[{i}] = {value} outside [0, {checks.highs[which, 0]:g}]"


def command_problem(p, checks: CommandChecks = _CHECKS) -> str | None:
    """What is wrong with the command packet ``p`` (None: nothing), its numbers checked in
    ``checks``' buffers (where they are left)."""
    if not isinstance(p, CommandPacket):
        return f"not a CommandPacket ({type(p).__name__})"
    seq = p.seq
    if isinstance(seq, bool) or not isinstance(seq, (int, np.integer)):
        return f"seq is not an integer ({seq!r})"
    if seq < 0:
        return f"seq is negative ({seq})"
    mode = p.requested_mode
    try:
        known = not isinstance(mode, bool) and mode in _MODE_VALUES
    except TypeError:  # unhashable
        known = False
    if not known:
        return f"requested_mode is not a ControlMode ({mode!r})"
    # joint positions when the command has them or its mode needs them; the joint
    # impedance only as the command carries it (None leaves the KRC's own values)
    needs_joints = p.jnt_pos is not None or mode == ControlMode.POSITION or mode == ControlMode.JNT_IMP
    originals = [p.cart_pos, p.cart_stiffness, p.cart_damping, p.add_tcp_ft, p.jnt_pos, p.jnt_stiffness,
                 p.jnt_damping, p.add_jnt_trq]
    kept: list = [None] * 8
    for which, (name, n, _) in enumerate(_VECTORS):
        value = originals[which]
        if which > 4 and value is None or which == 4 and not needs_joints:
            continue
        kept[which], why = _float_vector(value, n, name)
        if why:
            # a problem with the numbers before this vector comes first, as they are checked in order
            return _numbers_problem(originals, kept, checks) or why
    return _numbers_problem(originals, kept, checks)


def control_mode_or_value(mode):
    """``mode`` as a ControlMode if it is one, else as it came (a packet's checks then say
    so: ``command_problem``)."""
    try:
        return ControlMode(mode)
    except (ValueError, TypeError):
        return mode


def is_integer(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


@dataclass(slots=True, eq=False)
class MeasurementExtras:
    """What a measurement datagram carries beyond a ``MeasurementPacket``.

    None for the commanded positions means "the measured ones" (what a KRC holding
    its pose in monitor mode reports: a remote mirrors these before it commands, so
    they must be consistent and non-zero); the offsets FRI added default to zero
    (nothing added).  Arrays are in FRI's orders: ``jacobian`` rows X Y Z RZ RY RX
    (:func:`fri_order`).
    """

    cmd_jnt_pos: np.ndarray | None = None  # (7,) rad, commanded before FRI's offset
    cmd_jnt_pos_fri_offset: np.ndarray | None = None  # (7,)
    cmd_cart_pos: np.ndarray | None = None  # (12,) commanded before FRI
    cmd_cart_pos_fri_offset: np.ndarray | None = None  # (12,)
    msr_jnt_trq: np.ndarray | None = None  # (7,) Nm
    est_ext_jnt_trq: np.ndarray | None = None  # (7,) Nm
    jacobian: np.ndarray | None = None  # (6, 7) FRI row order
    mass_matrix: np.ndarray | None = None  # (7, 7)
    gravity: np.ndarray | None = None  # (7,) Nm
    temperature: np.ndarray | None = None  # (7,)
    miss_counter: int = 0  # intf.stat.missCounter
    sample_time_s: float = FRI_CYCLE_NS * 1e-9  # desiredMsrSampleTime and desiredCmdSampleTime
    safety_limits: float = 0.0
    power: int = ALL_DRIVES_POWERED
    error: int = 0
    warning: int = 0
