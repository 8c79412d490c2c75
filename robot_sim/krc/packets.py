"""The FRI 1.0 packets as the KRC judges them: the link's states and qualities, the
control modes, the measurement the KRC sends and the command a remote answers with, and
the checks a command must pass before the KRC will apply it (limits of the LWR4+'s
Cartesian impedance from the FRI 1.0 documentation).  Pure values: no sockets, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

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


def _vector(value, n: int, name: str) -> tuple[list | None, str | None]:
    """The values of a length-n float vector as a list, or a reason it is not one.

    Lists of Python floats make the handful of range checks below cheaper than
    numpy reductions on 6-12 element arrays.
    """
    if value is None:
        return None, f"{name} is missing"
    if isinstance(value, np.ndarray):
        if value.shape != (n,):
            return None, f"{name} has shape {value.shape}, expected ({n},)"
        if value.dtype.kind not in "fiu":
            return None, f"{name} has dtype {value.dtype}, expected float"
        values = value.tolist()
    else:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            return None, f"{name} is not numeric ({type(value).__name__})"
        if arr.shape != (n,):
            return None, f"{name} has shape {arr.shape}, expected ({n},)"
        values = arr.tolist()
    # A finite sum implies finite terms (NaN and inf propagate); only when the sum is
    # not finite is the element-wise look needed, and then only for the message.
    if not math.isfinite(sum(values)):
        bad = [i for i, v in enumerate(values) if not math.isfinite(v)]
        if bad:
            return None, f"{name}[{bad[0]}] is not finite ({values[bad[0]]})"
        return None, f"{name} has values too large to be meaningful"
    return values, None


def command_problem(p) -> str | None:
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

    c, why = _vector(p.cart_pos, _CART, "cart_pos")
    if why:
        return why
    # Rows of R are c[0:3], c[4:7], c[8:11]; c[3], c[7], c[11] are the position.
    a0, a1, a2, _, b0, b1, b2, _, c0, c1, c2, _ = c
    tol = ROTATION_TOLERANCE
    if (abs(a0 * a0 + a1 * a1 + a2 * a2 - 1.0) > tol or abs(b0 * b0 + b1 * b1 + b2 * b2 - 1.0) > tol
            or abs(c0 * c0 + c1 * c1 + c2 * c2 - 1.0) > tol or abs(a0 * b0 + a1 * b1 + a2 * b2) > tol
            or abs(a0 * c0 + a1 * c1 + a2 * c2) > tol or abs(b0 * c0 + b1 * c1 + b2 * c2) > tol):
        return "cart_pos rotation is not orthonormal"
    det = a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)
    if abs(det - 1.0) > tol:
        return f"cart_pos rotation has determinant {det:.6g}, expected 1"

    k, why = _vector(p.cart_stiffness, _FT, "cart_stiffness")
    if why:
        return why
    for i, v in enumerate(k):
        limit = MAX_TRANSLATIONAL_STIFFNESS if i < 3 else MAX_ROTATIONAL_STIFFNESS
        if not 0.0 <= v <= limit:
            return f"cart_stiffness[{i}] = {v} outside [0, {limit}]"

    d, why = _vector(p.cart_damping, _FT, "cart_damping")
    if why:
        return why
    for i, v in enumerate(d):
        if not 0.0 <= v <= 1.0:
            return f"cart_damping[{i}] = {v} outside [0, 1]"

    _, why = _vector(p.add_tcp_ft, _FT, "add_tcp_ft")
    if why:
        return why

    if p.jnt_pos is not None or mode == ControlMode.POSITION or mode == ControlMode.JNT_IMP:
        _, why = _vector(p.jnt_pos, _JNT, "jnt_pos")
        if why:
            return why
    # joint impedance: only what the command carries (None leaves the KRC's own values)
    for value, name, limit in ((p.jnt_stiffness, "jnt_stiffness", MAX_JOINT_STIFFNESS),
                               (p.jnt_damping, "jnt_damping", 1.0), (p.add_jnt_trq, "add_jnt_trq", None)):
        if value is None:
            continue
        values, why = _vector(value, _JNT, name)
        if why:
            return why
        if limit is not None:
            for i, v in enumerate(values):
                if not 0.0 <= v <= limit:
                    return f"{name}[{i}] = {v} outside [0, {limit:g}]"
    return None


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
