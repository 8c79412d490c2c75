"""The KUKA FRI 1.0 link as the KRC (robot controller) sees it.

What is modelled
----------------
The KRC sends one *measurement* packet per FRI cycle (1-100 ms, 1 ms here by
default) and expects the remote side to answer it with a *command* packet that
echoes the measurement's sequence number before the cycle ends.  This module
keeps the KRC's books on that exchange and decides what the controller applies
each cycle.  It is pure logic: no sockets, no physics, no threads and no clock.
Every call takes the time as an integer number of nanoseconds, so a test (or
the lockstep clock) can drive it with synthetic times.

- Sequence numbers.  Each measurement gets the next ``seq`` (the first one
  after construction is 1, so a default-initialised echo of 0 never matches).
  ``seq`` keeps counting across ``stop()``/``start()`` so that a stale answer
  from an earlier session can never pass for a current one.
  ``reflected_seq`` is the echo of the most recent well-formed command packet
  that reached the KRC in this session (in time or late), -1 if none yet.
- Deadline.  The answer to measurement ``seq`` sent at ``t`` is *in time* only
  if it arrives at ``t_arrival < t + cycle`` while ``seq`` is still the current
  cycle.  Answers to older seqs or arriving at/after the deadline are counted
  as *late* and ignored; packets failing ``CommandPacket.is_valid`` (or echoing
  a seq that was never sent, or arriving before their measurement was sent) are
  counted as *corrupt* and ignored; a second in-time answer to the same seq is
  counted as a *duplicate* and ignored (the first one wins).  A cycle without
  an accepted in-time answer is *missed*.  Bad packets never raise.
- Statistics over the last ``window`` (100) closed cycles: answer rate
  (in-time answers / cycles), miss rate (1 - answer rate), mean latency and
  jitter (population standard deviation of latency).  Latency is
  ``arrival - send time`` of the measurement answered and is recorded for every
  well-formed answer whose cycle is still in the window, late ones included:
  the latency figures describe the link, the miss rate describes the deadline.
  Latencies are kept as integer nanoseconds, so the sums are exact.
  With no closed cycle yet all four figures are 0.0; with no latency in the
  window the latency and jitter are 0.0 (0.0 rather than NaN keeps the
  published messages valid JSON).
- Quality, computed at every ``end_cycle`` from the packets in the window.  At
  start-up the window is short: quality is judged on the closed cycles seen so
  far (one missed cycle out of three is 33 %), and with none it is
  UNACCEPTABLE (nothing is known about the link yet).  Defaults
  (``FriConfig`` fields in brackets):

  ============  ==========================================================
  PERFECT       no miss in the window, mean latency < 0.5 cycle
                [perfect_max_latency_cycles] and jitter < 0.25 cycle
                [perfect_max_jitter_cycles]
  OK            miss rate <= 2 % [ok_max_miss_rate]
  BAD           miss rate <= 10 % [bad_max_miss_rate]
  UNACCEPTABLE  anything worse
  ============  ==========================================================

- States.  OFF -> MON on ``start()``.  MON -> CMD at the end of a cycle once
  ``request_command_mode()`` has been called and quality has been PERFECT for
  ``perfect_hold_cycles`` consecutive closed cycles (the run is counted whether
  or not a request is pending, so a request on a link that has long been
  PERFECT takes effect at the next ``end_cycle``).  CMD -> MON when quality
  falls below OK (the request is cleared: a new ``request_command_mode()`` is
  needed) or on ``request_monitor_mode()``.  Any state -> OFF on ``stop()``.
- What is applied (``CycleOutcome``).  In OFF and MON: no command, hold the
  pose.  In CMD: the cycle's accepted answer; if it is missing and at most
  ``max_bridged_misses`` consecutive cycles are missing, the last command
  applied in this CMD session is repeated (``bridged``); more consecutive
  misses, or no command applied yet in this CMD session, mean hold.  A command
  whose ``requested_mode`` differs from the KRC's control mode is not applied
  either (hold; counted as ``mode_mismatch``): the transport worked, so it
  does not count as a miss.
- Control mode (POSITION / CART_IMP / JNT_IMP) is switched by the KRC side with
  ``switch_control_mode`` and only in MON, as in FRI 1.0.
- Faults (``LinkFaults``): delay, uniform jitter, loss, corruption,
  duplication and reordering of command packets, and loss of measurement
  packets, from an explicit seed, optionally only within a window of time.

Order of calls per cycle
------------------------
::

    m = link.measurement(t, q, x, wrench)      # KRC sends; cycle seq m.seq opens
    m = link.deliver_measurement(m)            # optional: None if the fault hook lost it
    link.receive(cmd, t_arrival)               # remote's answer (or link.deliver(cmd, t_sent))
    out = link.end_cycle(t + link.config.cycle_ns)   # KRC closes the cycle, applies out.command

``receive`` may be called for any arrival time: the arrival time, not the order
of calls, decides whether an answer is in time, so a fault hook can hand over a
delayed packet at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from dataclasses import fields as dataclasses_fields
from enum import IntEnum

import numpy as np

# The KRC's FRI cycle in this testbench: 1 ms, the rate of the thesis' lab (FRI 1.0 allows
# 1..100 ms).  The physics steps once per cycle; every layer takes the cycle from here.
FRI_CYCLE_NS = 1_000_000
FRI_RATE_HZ = 1_000_000_000 // FRI_CYCLE_NS  # FRI cycles per second

__all__ = [
    "FriState",
    "FriQuality",
    "ControlMode",
    "MeasurementPacket",
    "CommandPacket",
    "FriConfig",
    "CycleOutcome",
    "FriStatistics",
    "LinkFaults",
    "FriLink",
    "MAX_TRANSLATIONAL_STIFFNESS",
    "MAX_ROTATIONAL_STIFFNESS",
    "MAX_JOINT_STIFFNESS",
    "ROTATION_TOLERANCE",
]

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
            reason = _command_problem(self)
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


def _command_problem(p) -> str | None:
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


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


@dataclass(frozen=True)
class FriConfig:
    """Timing, window and quality thresholds of the link.

    Quality thresholds (see the module docstring):
    PERFECT needs no miss in the window, mean latency below
    ``perfect_max_latency_cycles`` cycles and jitter below
    ``perfect_max_jitter_cycles`` cycles; OK needs miss rate <=
    ``ok_max_miss_rate``; BAD needs miss rate <= ``bad_max_miss_rate``;
    anything worse is UNACCEPTABLE.
    """

    cycle_ns: int = FRI_CYCLE_NS  # FRI 1.0 allows 1..100 ms
    window: int = 100  # packets the statistics and quality are taken over
    perfect_hold_cycles: int = 500  # consecutive PERFECT cycles before MON -> CMD
    perfect_max_latency_cycles: float = 0.5
    perfect_max_jitter_cycles: float = 0.25
    ok_max_miss_rate: float = 0.02
    bad_max_miss_rate: float = 0.10
    max_bridged_misses: int = 1  # consecutive missing answers covered by repeating the last command
    initial_control_mode: ControlMode = ControlMode.CART_IMP  # the testbench runs Cartesian impedance

    def __post_init__(self):
        def need(ok: bool, name: str, what: str):
            if not ok:
                raise ValueError(f"FriConfig.{name} = {getattr(self, name)!r}: {what}")

        need(_is_int(self.cycle_ns), "cycle_ns", "must be an integer number of nanoseconds")
        need(1_000_000 <= self.cycle_ns <= 100_000_000, "cycle_ns", "must be within 1 ms..100 ms (1_000_000..100_000_000 ns)")
        need(_is_int(self.window) and self.window >= 1, "window", "must be an integer >= 1")
        need(_is_int(self.perfect_hold_cycles) and self.perfect_hold_cycles >= 1, "perfect_hold_cycles", "must be an integer >= 1")
        need(_is_int(self.max_bridged_misses) and self.max_bridged_misses >= 0, "max_bridged_misses", "must be an integer >= 0")
        for name in ("perfect_max_latency_cycles", "perfect_max_jitter_cycles"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and math.isfinite(v) and v > 0, name, "must be a positive number of cycles")
        for name in ("ok_max_miss_rate", "bad_max_miss_rate"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and 0.0 <= v <= 1.0, name, "must be a fraction in [0, 1]")
        need(self.ok_max_miss_rate <= self.bad_max_miss_rate, "ok_max_miss_rate",
             f"must not exceed bad_max_miss_rate ({self.bad_max_miss_rate})")
        try:
            object.__setattr__(self, "initial_control_mode", ControlMode(self.initial_control_mode))
        except ValueError:
            need(False, "initial_control_mode", "must be a ControlMode")


@dataclass(slots=True, frozen=True, eq=False)
class CycleOutcome:
    """What the KRC applies in the cycle just closed."""

    seq: int  # the cycle (measurement seq) that was closed
    answered: bool  # an in-time, well-formed answer arrived
    command: CommandPacket | None  # what the controller applies; None with hold
    bridged: bool  # command is the previous one, repeated over a missing answer
    hold: bool  # no usable command: the arm holds its pose
    state: FriState  # state after this cycle's transitions
    quality: FriQuality
    consecutive_misses: int


@dataclass(frozen=True)
class FriStatistics:
    """Counters since the last ``start()`` and figures over the window."""

    sent: int  # measurements sent (the open cycle included)
    answered: int  # cycles closed with an in-time answer
    missed: int  # cycles closed without one
    late: int  # well-formed answers that came after their deadline or for an older cycle
    corrupt: int  # packets rejected as malformed / for a seq never sent / before their measurement
    duplicate: int  # extra in-time answers to an already answered cycle
    mode_mismatch: int  # CMD cycles whose command asked for another control mode
    bridged: int  # CMD cycles that repeated the last command
    held: int  # CMD cycles that held the pose
    longest_miss_run: int
    consecutive_misses: int
    window_packets: int  # closed cycles in the window (< window at start-up)
    answer_rate: float
    miss_rate: float
    latency_s: float
    jitter_s: float
    state: FriState
    quality: FriQuality


@dataclass
class LinkFaults:
    """Seeded faults on the path between KRC and remote.

    Command packets (remote -> KRC): lost with ``drop_probability``; otherwise
    damaged with ``corrupt_probability`` (one ``cart_pos`` element becomes NaN, on
    a copy) and delivered ``delay_ns`` plus a uniform 0..``jitter_ns`` later.
    A delivered command packet also arrives a second time with
    ``duplicate_probability`` (an exact copy, a uniform 0..``duplicate_spread_ns``
    after the first: the KRC must not apply it twice), and is held back
    ``reorder_lag_ns`` more with ``reorder_probability`` (1.5 ms by default: past
    its own deadline and after the next cycle's answer, so it arrives out of order).
    Measurement packets (KRC -> remote) are lost with
    ``measurement_drop_probability``: the remote never sees them and so cannot
    answer.  Each kind of packet draws from its own stream, a fixed number of
    draws per packet, so the same seed and the same calls give the same faults,
    and changing one probability does not reshuffle the others.  While ``active``
    is False (outside a scenario's fault window) the draws are made and ignored:
    packets pass untouched and the streams stay where a whole-run fault has them.
    """

    seed: int
    delay_ns: int = 0
    jitter_ns: int = 0
    drop_probability: float = 0.0
    corrupt_probability: float = 0.0
    measurement_drop_probability: float = 0.0
    duplicate_probability: float = 0.0
    duplicate_spread_ns: int = FRI_CYCLE_NS
    reorder_probability: float = 0.0
    reorder_lag_ns: int = 1_500_000
    active: bool = True
    dropped: int = field(default=0, init=False)
    corrupted: int = field(default=0, init=False)
    duplicated: int = field(default=0, init=False)
    reordered: int = field(default=0, init=False)
    measurements_dropped: int = field(default=0, init=False)
    _cmd_rng: np.random.Generator = field(init=False, repr=False, compare=False)
    _msr_rng: np.random.Generator = field(init=False, repr=False, compare=False)
    _order_rng: np.random.Generator = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        def need(ok: bool, name: str, what: str):
            if not ok:
                raise ValueError(f"LinkFaults.{name} = {getattr(self, name)!r}: {what}")

        need(_is_int(self.seed), "seed", "must be an integer (faults are always seeded)")
        need(_is_int(self.delay_ns) and self.delay_ns >= 0, "delay_ns", "must be an integer >= 0")
        need(_is_int(self.jitter_ns) and self.jitter_ns >= 0, "jitter_ns", "must be an integer >= 0")
        for name in ("duplicate_spread_ns", "reorder_lag_ns"):
            need(_is_int(getattr(self, name)) and getattr(self, name) >= 0, name, "must be an integer >= 0")
        for name in ("drop_probability", "corrupt_probability", "measurement_drop_probability",
                     "duplicate_probability", "reorder_probability"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and 0.0 <= v <= 1.0, name, "must be a probability in [0, 1]")
        # spawn keys are positional: the first two streams are what they were before the third existed
        cmd_seq, msr_seq, order_seq = np.random.SeedSequence(self.seed).spawn(3)
        self._cmd_rng = np.random.default_rng(cmd_seq)
        self._msr_rng = np.random.default_rng(msr_seq)
        self._order_rng = np.random.default_rng(order_seq)

    def measurement_lost(self) -> bool:
        """Whether the next measurement packet is lost on its way to the remote."""
        if self._msr_rng.random() < self.measurement_drop_probability and self.active:
            self.measurements_dropped += 1
            return True
        return False

    def transmit(self, packet: CommandPacket, t_sent_ns: int) -> list[tuple[CommandPacket, int]]:
        """Each arrival of ``packet`` as (packet as it arrives, arrival time), in order of
        arrival: none if it is lost, two if it is duplicated."""
        u_drop, u_corrupt, u_jitter, u_index = self._cmd_rng.random(4).tolist()
        u_dup, u_spread, u_reorder = self._order_rng.random(3).tolist() if self._orders else (1.0, 0.0, 1.0)
        if not self.active:
            return [(packet, int(t_sent_ns))]
        if u_drop < self.drop_probability:
            self.dropped += 1
            return []
        arrival = int(t_sent_ns) + self.delay_ns + (int(u_jitter * (self.jitter_ns + 1)) if self.jitter_ns else 0)
        if u_reorder < self.reorder_probability:
            self.reordered += 1
            arrival += self.reorder_lag_ns
        if u_corrupt < self.corrupt_probability:
            self.corrupted += 1
            try:
                damaged = np.array(packet.cart_pos, dtype=np.float64)
                damaged.reshape(-1)[int(u_index * damaged.size)] = np.nan
                packet = replace(packet, cart_pos=damaged)
            except Exception:
                pass  # already beyond repair: deliver it as it is, the KRC rejects it anyway
        if u_dup < self.duplicate_probability:
            self.duplicated += 1
            return [(packet, arrival), (packet, arrival + int(u_spread * (self.duplicate_spread_ns + 1)))]
        return [(packet, arrival)]

    @property
    def _orders(self) -> bool:
        # the third stream is drawn only where it is used: a run without these faults
        # costs nothing more per packet
        return self.duplicate_probability > 0.0 or self.reorder_probability > 0.0


class LinkFaultError(ValueError):
    """A fault specification that cannot be used: ``field`` (e.g. ``packet_loss``), what is
    expected (``problem``) and the ``value``."""

    def __init__(self, field_name: str, problem: str, value):
        super().__init__(f"{field_name}: {problem}, got {value!r}")
        self.field, self.problem, self.value = field_name, problem, value


_PROBABILITY, _MS, _SECONDS = "probability", "ms", "seconds"


def _fault(default: float, kind: str, doc: str):
    return field(default=default, metadata={"kind": kind, "doc": doc})


@dataclass(frozen=True)
class LinkFaultSpec:
    """The FRI link's faults as a study sets them, checked here once: a scenario's
    ``cell.fri_<field>`` and the robot's ``--fri-<field>`` flags are these fields.
    ``link_faults`` is the seeded model of them (``LinkFaults``), ``active`` the window."""

    packet_loss: float = _fault(0.0, _PROBABILITY, "probability that a command packet is lost on the FRI link")
    delay_ms: float = _fault(0.0, _MS, "every command packet arrives this much later, ms")
    jitter_ms: float = _fault(0.0, _MS, "and a further uniform 0..this, ms (reorders late answers)")
    corruption: float = _fault(0.0, _PROBABILITY, "probability that a command packet arrives damaged (the KRC "
                                                  "rejects it)")
    duplication: float = _fault(0.0, _PROBABILITY, "probability that a command packet arrives twice (the copy "
                                                   "0..1 cycle after it)")
    reordering: float = _fault(0.0, _PROBABILITY, "probability that a command packet is held back 1.5 ms (it "
                                                  "arrives after the next cycle's)")
    faults_from_s: float = _fault(0.0, _SECONDS, "the faults act from this many seconds into each episode")
    faults_until_s: float = _fault(math.inf, _SECONDS, "... until this many seconds into it (default: to its end)")

    MAX_DELAY_MS = 1000.0

    def __post_init__(self):
        for f in dataclasses_fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                    or math.isnan(value):
                raise LinkFaultError(f.name, "expected a number", value)
            kind = f.metadata["kind"]
            if kind == _PROBABILITY and not 0.0 <= value <= 1.0:
                raise LinkFaultError(f.name, "expected a probability in [0, 1]", value)
            if kind == _MS and not 0.0 <= value <= self.MAX_DELAY_MS:
                raise LinkFaultError(f.name, f"expected a number of ms in [0, {self.MAX_DELAY_MS:g}]", value)
            if f.name == "faults_from_s" and not 0.0 <= value < math.inf:
                raise LinkFaultError(f.name, "expected a finite number of seconds >= 0", value)
            object.__setattr__(self, f.name, float(value))
        if not self.faults_until_s > self.faults_from_s:
            raise LinkFaultError("faults_until_s", f"expected a number of seconds > the window's start "
                                                   f"({self.faults_from_s})", self.faults_until_s)

    def link_faults(self, seed: int) -> LinkFaults | None:
        """The seeded fault model, or None when the link is clean."""
        if not (self.packet_loss or self.corruption or self.duplication or self.reordering or self.delay_ms
                or self.jitter_ms):
            return None
        return LinkFaults(seed=seed, drop_probability=self.packet_loss, delay_ns=round(self.delay_ms * 1e6),
                          jitter_ns=round(self.jitter_ms * 1e6), corrupt_probability=self.corruption,
                          duplicate_probability=self.duplication, reorder_probability=self.reordering)

    def active(self, episode_s: float) -> bool:
        """Whether the faults act ``episode_s`` seconds into an episode."""
        return self.faults_from_s <= episode_s < self.faults_until_s


_NO_LATENCY = -1


class FriLink:
    """The KRC's end of one FRI 1.0 connection.  See the module docstring."""

    def __init__(self, config: FriConfig | None = None, faults: LinkFaults | None = None):
        self.config = config if config is not None else FriConfig()
        self.faults = faults
        self._seq = 0  # last seq sent; kept across sessions (see module docstring)
        self._control_mode = self.config.initial_control_mode
        self._state = FriState.OFF
        self._reset_session(0)

    # ----------------------------------------------------------------- session
    def _reset_session(self, t_ns: int) -> None:
        w = self.config.window
        self._started_ns = t_ns
        self._first_seq = self._seq + 1
        self._quality = FriQuality.UNACCEPTABLE
        self._cmd_requested = False
        self._perfect_run = 0
        self._last_applied: CommandPacket | None = None
        self._reflected_seq = -1
        # The open cycle.
        self._open = False
        self._deadline_ns = t_ns
        self._cur_cmd: CommandPacket | None = None
        self._cur_lat = _NO_LATENCY
        # Window of closed cycles, a ring indexed by seq % window (seqs are consecutive
        # within a session, so pushing seq s evicts s - window).  Plain lists: scalar
        # access to Python lists is several times faster than to numpy arrays.
        self._w_seq = [-1] * w
        self._w_missed = [False] * w
        self._w_lat = [_NO_LATENCY] * w
        self._w_n = 0
        self._w_misses = 0
        self._lat_n = 0
        self._lat_sum = 0  # integer ns: exact, no drift over long runs
        self._lat_sq = 0
        # Send times of the open cycle and the window's cycles, for late answers' latency.
        self._send_seq = [-1] * (w + 1)
        self._send_ns = [0] * (w + 1)
        # Counters since start().
        self._sent = self._answered = self._missed = self._late = self._corrupt = 0
        self._duplicate = self._mode_mismatch = self._bridged = self._held = 0
        self._consecutive = self._longest_run = 0
        self.last_reject_reason = ""

    def start(self, t_ns: int) -> None:
        """OFF -> MON.  Resets statistics, quality and any command request."""
        if self._state != FriState.OFF:
            raise RuntimeError(f"FriLink.start: link is already {self._state.name}; stop() it first")
        self._reset_session(int(t_ns))
        self._state = FriState.MON

    def stop(self) -> None:
        """Any state -> OFF.  An open cycle is abandoned; statistics stay readable."""
        self._state = FriState.OFF
        self._open = False
        self._cur_cmd = None
        self._cmd_requested = False
        self._last_applied = None

    def request_command_mode(self) -> bool:
        """Ask for CMD; it is entered once quality has been PERFECT long enough.  False in OFF."""
        if self._state == FriState.OFF:
            return False
        if self._state == FriState.MON:
            self._cmd_requested = True
        return True

    def request_monitor_mode(self) -> bool:
        """CMD -> MON now (and forget a pending request).  False in OFF."""
        if self._state == FriState.OFF:
            return False
        self._cmd_requested = False
        if self._state == FriState.CMD:
            self._leave_cmd()
        return True

    def switch_control_mode(self, mode: ControlMode) -> bool:
        """Change the control mode; FRI allows this only in MON (False otherwise, nothing changes)."""
        mode = ControlMode(mode)  # an unknown mode is a programming error: ValueError
        if self._state != FriState.MON:
            return False
        self._control_mode = mode
        return True

    def _leave_cmd(self) -> None:
        self._state = FriState.MON
        self._cmd_requested = False
        self._last_applied = None  # bridging must never reach back into an earlier CMD session

    # --------------------------------------------------------------- read-outs
    @property
    def state(self) -> FriState:
        return self._state

    @property
    def quality(self) -> FriQuality:
        return self._quality

    @property
    def control_mode(self) -> ControlMode:
        return self._control_mode

    @property
    def seq(self) -> int:
        """Seq of the last measurement sent (0 before the first)."""
        return self._seq

    @property
    def last_applied(self) -> CommandPacket | None:
        """The command the KRC applied last in this CMD session (None in MON)."""
        return self._last_applied

    @property
    def command_requested(self) -> bool:
        return self._cmd_requested

    @property
    def consecutive_misses(self) -> int:
        return self._consecutive

    def _window_figures(self) -> tuple[float, float, float, float]:
        """(answer_rate, miss_rate, latency_s, jitter_s) over the window."""
        n = self._w_n
        if n == 0:
            return 0.0, 0.0, 0.0, 0.0
        miss_rate = self._w_misses / n
        ln = self._lat_n
        if ln == 0:
            return 1.0 - miss_rate, miss_rate, 0.0, 0.0
        # n*sum(x^2) - sum(x)^2 is exact in integers, so the variance is never negative.
        var_num = ln * self._lat_sq - self._lat_sum * self._lat_sum
        return (1.0 - miss_rate, miss_rate, self._lat_sum / ln * 1e-9, math.sqrt(var_num) / ln * 1e-9)

    def statistics(self) -> FriStatistics:
        answer_rate, miss_rate, latency_s, jitter_s = self._window_figures()
        return FriStatistics(
            sent=self._sent, answered=self._answered, missed=self._missed, late=self._late,
            corrupt=self._corrupt, duplicate=self._duplicate, mode_mismatch=self._mode_mismatch,
            bridged=self._bridged, held=self._held, longest_miss_run=self._longest_run,
            consecutive_misses=self._consecutive, window_packets=self._w_n,
            answer_rate=answer_rate, miss_rate=miss_rate, latency_s=latency_s, jitter_s=jitter_s,
            state=self._state, quality=self._quality,
        )

    # ------------------------------------------------------------------- cycle
    def measurement(self, t_ns: int, msr_jnt_pos, msr_cart_pos, est_ext_tcp_ft) -> MeasurementPacket:
        """Open the cycle at ``t_ns`` and return the packet the KRC sends."""
        t_ns = int(t_ns)
        if self._state == FriState.OFF:
            raise RuntimeError("FriLink.measurement: link is OFF; call start() first")
        if self._open:
            raise RuntimeError(f"FriLink.measurement: cycle seq {self._seq} is still open; call end_cycle() first")
        if self._seq >= self._first_seq and t_ns < self._deadline_ns:
            raise ValueError(f"FriLink.measurement: t_ns = {t_ns} is before the previous cycle's deadline {self._deadline_ns}")
        q = np.array(msr_jnt_pos, dtype=np.float64)
        x = np.array(msr_cart_pos, dtype=np.float64)
        ft = np.array(est_ext_tcp_ft, dtype=np.float64)
        if q.shape != (_JNT,) or x.shape != (_CART,) or ft.shape != (_FT,):
            raise ValueError(
                f"FriLink.measurement: shapes msr_jnt_pos {q.shape}, msr_cart_pos {x.shape}, "
                f"est_ext_tcp_ft {ft.shape}; expected (7,), (12,), (6,)")

        self._seq += 1
        seq = self._seq
        j = seq % (self.config.window + 1)
        self._send_seq[j] = seq
        self._send_ns[j] = t_ns
        self._open = True
        self._deadline_ns = t_ns + self.config.cycle_ns
        self._cur_cmd = None
        self._cur_lat = _NO_LATENCY
        self._sent += 1

        answer_rate, miss_rate, latency_s, jitter_s = self._window_figures()
        return MeasurementPacket(
            seq, self._reflected_seq, t_ns, self._state, self._quality, self._control_mode,
            q, x, ft, answer_rate, latency_s, jitter_s, miss_rate,
        )

    def deliver_measurement(self, m: MeasurementPacket) -> MeasurementPacket | None:
        """``m`` as the remote gets it: None if the fault hook lost it."""
        if self.faults is not None and self.faults.measurement_lost():
            return None
        return m

    def _reject(self, reason: str) -> bool:
        self.last_reject_reason = reason
        return False

    def receive(self, packet: CommandPacket, t_ns: int, *, owned: bool = False) -> bool:
        """A command packet arrives at ``t_ns``.  True if accepted as this cycle's answer.
        ``owned``: the caller made the packet for this call, float64 arrays nobody else
        holds and a ControlMode (what ``CommandPacket.copy`` makes): it is kept as it is."""
        t_ns = int(t_ns)
        if self._state == FriState.OFF:
            return self._reject("link is OFF")
        try:
            problem = _command_problem(packet)
        except Exception as exc:
            problem = f"unreadable packet ({type(exc).__name__}: {exc})"
        if problem is not None:
            self._corrupt += 1
            return self._reject(problem)
        s = int(packet.seq)
        if s > self._seq:
            self._corrupt += 1
            return self._reject(f"seq {s} was never sent (last sent {self._seq})")
        if s < self._first_seq:
            self._late += 1
            return self._reject(f"seq {s} belongs to an earlier session")

        j = s % (self.config.window + 1)
        known_send = self._send_seq[j] == s
        if known_send and t_ns < self._send_ns[j]:
            self._corrupt += 1
            return self._reject(f"arrived at {t_ns}, before measurement {s} was sent at {self._send_ns[j]}")
        self._reflected_seq = s
        latency = t_ns - self._send_ns[j] if known_send else _NO_LATENCY

        if s == self._seq and self._open:
            if t_ns < self._deadline_ns:
                if self._cur_cmd is not None:
                    self._duplicate += 1
                    return self._reject(f"duplicate answer to seq {s}")
                # A copy: the sender may reuse its buffers, the wire would not share them.
                self._cur_cmd = packet if owned else packet.copy()
                self._cur_lat = latency
                self.last_reject_reason = ""
                return True
            self._late += 1
            if self._cur_lat == _NO_LATENCY:
                self._cur_lat = latency
            return self._reject(f"answer to seq {s} arrived at {t_ns}, deadline {self._deadline_ns}")

        self._late += 1
        # The cycle is closed; its latency still belongs in the window if it is there.
        i = s % self.config.window
        if latency != _NO_LATENCY and self._w_seq[i] == s and self._w_lat[i] == _NO_LATENCY:
            self._w_lat[i] = latency
            self._lat_n += 1
            self._lat_sum += latency
            self._lat_sq += latency * latency
        return self._reject(f"answer to seq {s} arrived after its cycle closed (current seq {self._seq})")

    def deliver(self, packet: CommandPacket, t_sent_ns: int, *, owned: bool = False) -> bool:
        """Send ``packet`` from the remote at ``t_sent_ns`` through the fault hook, then
        ``receive`` it (``owned`` as there; through the faults, each arrival is copied)."""
        if self.faults is None:
            return self.receive(packet, t_sent_ns, owned=owned)
        accepted = False
        # each arrival is judged by its arrival time against the cycle it reaches: a copy
        # within the deadline is a duplicate, a packet held back past it is late
        for arrived, t_ns in self.faults.transmit(packet, t_sent_ns):
            accepted = self.receive(arrived, t_ns) or accepted
        return accepted

    def end_cycle(self, t_ns: int) -> CycleOutcome:
        """Close the open cycle at its deadline and decide what the KRC applies."""
        t_ns = int(t_ns)
        if not self._open:
            raise RuntimeError("FriLink.end_cycle: no open cycle; call measurement() first")
        if t_ns < self._deadline_ns:
            raise ValueError(f"FriLink.end_cycle: t_ns = {t_ns} is before the cycle's deadline {self._deadline_ns}")
        self._open = False
        seq = self._seq
        cmd = self._cur_cmd
        answered = cmd is not None

        # Window push (evicting seq - window).
        i = seq % self.config.window
        if self._w_seq[i] >= 0:
            if self._w_missed[i]:
                self._w_misses -= 1
            old = self._w_lat[i]
            if old != _NO_LATENCY:
                self._lat_n -= 1
                self._lat_sum -= old
                self._lat_sq -= old * old
        else:
            self._w_n += 1
        self._w_seq[i] = seq
        self._w_missed[i] = not answered
        lat = self._cur_lat
        self._w_lat[i] = lat
        if lat != _NO_LATENCY:
            self._lat_n += 1
            self._lat_sum += lat
            self._lat_sq += lat * lat

        if answered:
            self._answered += 1
            self._consecutive = 0
        else:
            self._w_misses += 1
            self._missed += 1
            self._consecutive += 1
            if self._consecutive > self._longest_run:
                self._longest_run = self._consecutive

        quality = self._quality = self._assess()
        self._perfect_run = self._perfect_run + 1 if quality == FriQuality.PERFECT else 0

        if self._state == FriState.CMD and quality < FriQuality.OK:
            self._leave_cmd()
        elif (self._state == FriState.MON and self._cmd_requested
              and self._perfect_run >= self.config.perfect_hold_cycles):
            self._state = FriState.CMD
            self._cmd_requested = False
            self._last_applied = None

        bridged = False
        applied = None
        if self._state == FriState.CMD:
            if answered:
                if cmd.requested_mode == self._control_mode:
                    applied = self._last_applied = cmd
                else:
                    self._mode_mismatch += 1
            elif self._consecutive <= self.config.max_bridged_misses and self._last_applied is not None:
                applied = self._last_applied
                bridged = True
                self._bridged += 1
            if applied is None:
                self._held += 1
        return CycleOutcome(seq, answered, applied, bridged, applied is None, self._state, quality, self._consecutive)

    def _assess(self) -> FriQuality:
        n = self._w_n
        if n == 0:
            return FriQuality.UNACCEPTABLE
        cfg = self.config
        misses = self._w_misses
        if misses == 0:
            ln = self._lat_n  # == n: every cycle in the window was answered in time
            cycle = cfg.cycle_ns
            mean_ok = self._lat_sum < cfg.perfect_max_latency_cycles * cycle * ln
            var = (ln * self._lat_sq - self._lat_sum * self._lat_sum) / (ln * ln)
            jitter_ok = var < (cfg.perfect_max_jitter_cycles * cycle) ** 2
            if mean_ok and jitter_ok:
                return FriQuality.PERFECT
            return FriQuality.OK
        # A small slack so that "at most 2 %" holds for exactly 2 of 100.
        if misses <= cfg.ok_max_miss_rate * n + 1e-9:
            return FriQuality.OK
        if misses <= cfg.bad_max_miss_rate * n + 1e-9:
            return FriQuality.BAD
        return FriQuality.UNACCEPTABLE
