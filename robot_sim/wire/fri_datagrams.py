"""The FRI 1.0 datagrams as bytes: the KRC's measurement and the remote's command.

The layouts are those of ``WIRE.md`` (KUKA's KR C2 lr FRI 1.0, the LWR4+ era, not the
later Sunrise FRI): little-endian, 4-byte packing, every float IEEE-754 float32.  They
live in one place, the numpy structured dtypes :data:`MEASUREMENT_DTYPE` (916 bytes,
``datagramId`` 0x2006, KRC -> remote) and :data:`COMMAND_DTYPE` (376 bytes, 0x1005,
remote -> KRC), built with explicit offsets and FRI's own field names, nested as FRI
nests them::

    measurement: head, krl, intf (with intf.stat), robot, data
    command:     head, krl, cmd

so ``rec["data"]["msrJntPos"]`` is the 7 float32 at byte 216.  :func:`field_offsets`
lists every field's byte offset from the dtype itself.

Byte offsets (from WIRE.md; the tests read each one back with ``struct``)::

    both    0 head.sendSeqCount u16   2 head.reflSeqCount u16   4 head.packetSize u16
            6 head.datagramId u16     8 krl.realData f32[16]   72 krl.intData i32[16]
          136 krl.boolData u16      138 krl.fill u16
    msr   140 intf.timestamp f32    144 intf.state u16        146 intf.quality u16
          148 intf.desiredMsrSampleTime f32                   152 intf.desiredCmdSampleTime f32
          156 intf.safetyLimits f32 160 intf.stat.answerRate  164 .latency  168 .jitter
          172 intf.stat.missRate    176 intf.stat.missCounter u32
          180 robot.power u16       182 robot.control u16     184 robot.error  186 robot.warning
          188 robot.temperature f32[7]
          216 data.msrJntPos[7]     244 data.msrCartPos[12]   292 data.cmdJntPos[7]
          320 data.cmdJntPosFriOffset[7]  348 data.cmdCartPos[12]  396 data.cmdCartPosFriOffset[12]
          444 data.msrJntTrq[7]     472 data.estExtJntTrq[7]  500 data.estExtTcpFT[6]
          524 data.jacobian[6][7]   692 data.massMatrix[7][7] 888 data.gravity[7]
    cmd   140 cmd.cmdFlags u32      144 cmd.jntPos[7]         172 cmd.cartPos[12]
          220 cmd.addJntTrq[7]      248 cmd.addTcpFT[6]       272 cmd.jntStiffness[7]
          300 cmd.jntDamping[7]     328 cmd.cartStiffness[6]  352 cmd.cartDamping[6]

Counters.  FRI's header counters are uint16 and wrap after 65536 cycles (65.5 s at
1 kHz); the testbench counts cycles with Python ints (``MeasurementPacket.seq``).  On
the wire a seq is ``seq & 0xFFFF`` (:func:`counter16`); :func:`unwrap` maps a
received 16-bit counter back to the full cycle number nearest a known one (the open
cycle, for a command's ``reflSeqCount``).  A ``reflected_seq`` of -1 (nothing
received yet) goes out as 0, as a KRC that has heard nothing reflects.

Orders.  FRI orders a wrench Fx, Fy, Fz, Tz, Ty, Tx and the rotational part of the
Cartesian stiffness and damping A, B, C (about Z, Y, X).  The testbench's packets
(``robot_sim.krc.packets``) keep the wrenches in FRI's order already (``est_ext_tcp_ft``,
``add_tcp_ft``; ``robot_sim.krc.packets.fri_order`` turns them into the law's), so the
wrenches cross unchanged; ``cart_stiffness`` and ``cart_damping`` are in the law's
order x, y, z, rx, ry, rz and are permuted here (:func:`robot_sim.krc.packets.fri_order`, its own inverse).
The Jacobian's rows go out X, Y, Z, RZ, RY, RX (:func:`jacobian_to_fri` from the
usual [v; w] rows).

Command flags and the control mode.  FRI 1.0's command carries no control mode: the
KRL program chose it before ``friStart``; ``cmdFlags`` only say which fields the
remote fills.  :func:`mode_for_flags` reads the mode the flags belong to (the KRC's
own mode when they fit it), and :func:`command_packet` turns a decoded command into a
``CommandPacket`` whose ``requested_mode`` that is, so the FriLink counts a command
that does not fit the KRC's mode as a mode mismatch, as it does any other.  Fields
the flags leave out come from the caller's ``defaults`` (the KRC's own values).
Joint stiffness, damping and added joint torque are carried when flagged (None
otherwise: the KRC's own values).

Errors.  :func:`decode_measurement` and :func:`decode_command` raise
:class:`FriWireError` (a ``ValueError``) for a datagram of the wrong length or
``datagramId``; the endpoint (``robot_sim.wire.fri_udp``) counts and ignores those.  The
header's ``packetSize`` is written on encode and not judged on decode (the length
of the datagram is).
"""

from __future__ import annotations

import struct
from enum import IntFlag

import numpy as np

from robot_sim.krc.krl import KRL_SIZE, KrlChannels
from robot_sim.krc.packets import (CommandPacket, ControlMode, FriQuality, FriState, MeasurementExtras,
                                   MeasurementPacket, fri_order)

__all__ = [
    "COMMAND_DTYPE",
    "COMMAND_ID",
    "COMMAND_SIZE",
    "HEADER_DTYPE",
    "KRL_DTYPE",
    "MEASUREMENT_DTYPE",
    "MEASUREMENT_ID",
    "MEASUREMENT_SIZE",
    "MODE_FLAGS",
    "REMOTE_PORT",
    "CommandFlags",
    "FriWireError",
    "command_packet",
    "counter16",
    "decode_command",
    "decode_measurement",
    "encode_command",
    "encode_measurement",
    "field_offsets",
    "measurement_packet",
    "mode_for_flags",
    "new_command",
    "new_measurement",
    "read_krl",
    "record_fields",
    "unwrap",
    "write_command",
    "write_krl",
    "write_measurement",
]

MEASUREMENT_SIZE = 916
MEASUREMENT_ID = 0x2006
COMMAND_SIZE = 376
COMMAND_ID = 0x1005
REMOTE_PORT = 49938  # where both public FRI 1.0 remote libraries listen by default

_J, _CART, _FT = 7, 12, 6
_COUNTER = 1 << 16

HEADER_DTYPE = np.dtype({
    "names": ["sendSeqCount", "reflSeqCount", "packetSize", "datagramId"],
    "formats": ["<u2", "<u2", "<u2", "<u2"],
    "offsets": [0, 2, 4, 6],
    "itemsize": 8,
})

KRL_DTYPE = np.dtype({
    "names": ["realData", "intData", "boolData", "fill"],
    "formats": [("<f4", (KRL_SIZE,)), ("<i4", (KRL_SIZE,)), "<u2", "<u2"],
    "offsets": [0, 64, 128, 130],
    "itemsize": 132,
})

_STAT_DTYPE = np.dtype({
    "names": ["answerRate", "latency", "jitter", "missRate", "missCounter"],
    "formats": ["<f4", "<f4", "<f4", "<f4", "<u4"],
    "offsets": [0, 4, 8, 12, 16],
    "itemsize": 20,
})

_INTF_DTYPE = np.dtype({
    "names": ["timestamp", "state", "quality", "desiredMsrSampleTime", "desiredCmdSampleTime",
              "safetyLimits", "stat"],
    "formats": ["<f4", "<u2", "<u2", "<f4", "<f4", "<f4", _STAT_DTYPE],
    "offsets": [0, 4, 6, 8, 12, 16, 20],
    "itemsize": 40,
})

_ROBOT_DTYPE = np.dtype({
    "names": ["power", "control", "error", "warning", "temperature"],
    "formats": ["<u2", "<u2", "<u2", "<u2", ("<f4", (_J,))],
    "offsets": [0, 2, 4, 6, 8],
    "itemsize": 36,
})

_DATA_DTYPE = np.dtype({
    "names": ["msrJntPos", "msrCartPos", "cmdJntPos", "cmdJntPosFriOffset", "cmdCartPos",
              "cmdCartPosFriOffset", "msrJntTrq", "estExtJntTrq", "estExtTcpFT", "jacobian",
              "massMatrix", "gravity"],
    "formats": [("<f4", (_J,)), ("<f4", (_CART,)), ("<f4", (_J,)), ("<f4", (_J,)), ("<f4", (_CART,)),
                ("<f4", (_CART,)), ("<f4", (_J,)), ("<f4", (_J,)), ("<f4", (_FT,)), ("<f4", (6, _J)),
                ("<f4", (_J, _J)), ("<f4", (_J,))],
    "offsets": [0, 28, 76, 104, 132, 180, 228, 256, 284, 308, 476, 672],
    "itemsize": 700,
})

MEASUREMENT_DTYPE = np.dtype({
    "names": ["head", "krl", "intf", "robot", "data"],
    "formats": [HEADER_DTYPE, KRL_DTYPE, _INTF_DTYPE, _ROBOT_DTYPE, _DATA_DTYPE],
    "offsets": [0, 8, 140, 180, 216],
    "itemsize": MEASUREMENT_SIZE,
})

_CMD_DTYPE = np.dtype({
    "names": ["cmdFlags", "jntPos", "cartPos", "addJntTrq", "addTcpFT", "jntStiffness", "jntDamping",
              "cartStiffness", "cartDamping"],
    "formats": ["<u4", ("<f4", (_J,)), ("<f4", (_CART,)), ("<f4", (_J,)), ("<f4", (_FT,)), ("<f4", (_J,)),
                ("<f4", (_J,)), ("<f4", (_FT,)), ("<f4", (_FT,))],
    "offsets": [0, 4, 32, 80, 108, 132, 160, 188, 212],
    "itemsize": 236,
})

COMMAND_DTYPE = np.dtype({
    "names": ["head", "krl", "cmd"],
    "formats": [HEADER_DTYPE, KRL_DTYPE, _CMD_DTYPE],
    "offsets": [0, 8, 140],
    "itemsize": COMMAND_SIZE,
})


class FriWireError(ValueError):
    """A datagram that is not the expected FRI 1.0 datagram: ``reason`` is ``"size"`` or
    ``"id"``; ``size`` its length, ``datagram_id`` its header's id (None if too short)."""

    def __init__(self, what: str, reason: str, size: int, datagram_id: int | None, expected: tuple[int, int]):
        exp_size, exp_id = expected
        if reason == "size":
            detail = f"{size} bytes, expected {exp_size}"
        else:
            detail = f"datagramId 0x{datagram_id:04x}, expected 0x{exp_id:04x}"
        super().__init__(f"not an FRI 1.0 {what} datagram: {detail}")
        self.reason, self.size, self.datagram_id = reason, size, datagram_id


class CommandFlags(IntFlag):
    """``cmd.cmdFlags``: which command fields the remote fills (WIRE.md).  The
    velocities (0x0002, 0x0200) are not supported by FRI 1.0 and have no member."""

    NONE = 0
    JNT_POS = 0x0001
    JNT_TRQ = 0x0004  # addJntTrq
    JNT_STIFF = 0x0010
    JNT_DAMP = 0x0020
    CART_POS = 0x0100
    TCP_FT = 0x0400  # addTcpFT
    CART_STIFF = 0x1000
    CART_DAMP = 0x2000
    # what each control mode takes (the Stanford library sends these whole)
    POSITION = JNT_POS
    JNT_IMP = JNT_POS | JNT_TRQ | JNT_STIFF | JNT_DAMP  # 0x0035
    CART_IMP = CART_POS | TCP_FT | CART_STIFF | CART_DAMP  # 0x3500


# the flags a command may carry in each control mode (a subset of them fits the mode)
MODE_FLAGS = {
    ControlMode.POSITION: CommandFlags.POSITION,
    ControlMode.JNT_IMP: CommandFlags.JNT_IMP,
    ControlMode.CART_IMP: CommandFlags.CART_IMP,
}

# the flags a CommandPacket is sent with, per requested mode: the fields it has
_PACKET_FLAGS = {
    ControlMode.POSITION: CommandFlags.JNT_POS,
    ControlMode.JNT_IMP: CommandFlags.JNT_POS,  # and the joint fields the packet holds (_packet_flags)
    ControlMode.CART_IMP: CommandFlags.CART_IMP,
    ControlMode.OTHER: CommandFlags.NONE,
}


def _packet_flags(cmd: CommandPacket) -> int:
    flags = _PACKET_FLAGS[ControlMode(cmd.requested_mode)]
    if cmd.requested_mode == ControlMode.JNT_IMP:
        for value, flag in ((cmd.jnt_stiffness, CommandFlags.JNT_STIFF), (cmd.jnt_damping, CommandFlags.JNT_DAMP),
                            (cmd.add_jnt_trq, CommandFlags.JNT_TRQ)):
            if value is not None:
                flags |= flag
    return int(flags)


def mode_for_flags(flags: int, current: ControlMode) -> ControlMode:
    """The control mode a command with ``flags`` is meant for.

    ``current`` (the KRC's mode) when the flags fit it (no flags fit every mode);
    otherwise the first of POSITION, JNT_IMP, CART_IMP they fit; OTHER when they fit
    none (unknown bits, or joint and Cartesian fields mixed).
    """
    flags = int(flags)
    current = ControlMode(current)
    allowed = MODE_FLAGS.get(current)
    if allowed is not None and flags & ~int(allowed) == 0:
        return current
    for mode, allowed in MODE_FLAGS.items():
        if flags & ~int(allowed) == 0:
            return mode
    return ControlMode.OTHER


# ----------------------------------------------------------------------- counters

def counter16(seq: int) -> int:
    """A cycle number as FRI's uint16 header counter."""
    return int(seq) & 0xFFFF


def unwrap(counter: int, near: int) -> int:
    """The full cycle number whose 16-bit counter is ``counter`` and that lies nearest
    ``near`` (within [near - 32768, near + 32767]: a tie goes to the past, the side a
    reflected counter lies on)."""
    counter = int(counter)
    if not 0 <= counter < _COUNTER:
        raise ValueError(f"unwrap: counter {counter} is not a uint16")
    near = int(near)
    return near + (counter - near + _COUNTER // 2) % _COUNTER - _COUNTER // 2


def record_fields(rec: np.ndarray) -> dict:
    """A decoded datagram as nested plain values with FRI's names (``{"head": {...},
    "data": {"msrJntPos": [...], ...}}``): arrays as (nested) lists, float32 as the
    float64 of the same value.  For recordings and logs, not the cycle."""
    def walk(value):
        fields = value.dtype.fields
        if fields is None:
            return value.tolist()
        return {name: walk(value[name]) for name in fields}

    return walk(rec)


def field_offsets(dtype: np.dtype) -> dict[str, tuple[int, np.dtype]]:
    """Every leaf field of a datagram dtype as ``{"data.msrJntPos": (byte offset, dtype)}``."""
    out: dict[str, tuple[int, np.dtype]] = {}

    def walk(dt: np.dtype, base: int, prefix: str) -> None:
        for name, (sub, offset) in dt.fields.items():
            path = f"{prefix}{name}"
            if sub.fields is not None:
                walk(sub, base + offset, path + ".")
            else:
                out[path] = (base + offset, sub)

    walk(np.dtype(dtype), 0, "")
    return out


# ------------------------------------------------------------------ KRL channels

def read_krl(rec: np.ndarray) -> KrlChannels:
    """The KRL block of a decoded datagram (either kind), as float64/int64 copies."""
    krl = rec["krl"]
    return KrlChannels(np.array(krl["realData"], dtype=np.float64), np.array(krl["intData"], dtype=np.int64),
                       int(krl["boolData"]))


def write_krl(rec: np.ndarray, krl: KrlChannels | None) -> None:
    """Write ``krl`` into a datagram record (zeros for None).  Integers must fit int32."""
    block = rec["krl"]
    if krl is None:
        block["realData"] = 0.0
        block["intData"] = 0
        block["boolData"] = 0
        return
    ints = np.asarray(krl.ints)
    if ints.shape != (KRL_SIZE,) or np.any(ints < -(1 << 31)) or np.any(ints >= 1 << 31):
        raise ValueError(f"KRL ints must be {KRL_SIZE} int32 values, got {krl.ints!r}")
    block["realData"] = krl.reals
    block["intData"] = ints
    if not 0 <= int(krl.bools) < _COUNTER:
        raise ValueError(f"KRL bools must fit 16 bits, got {krl.bools!r}")
    block["boolData"] = int(krl.bools)
    block["fill"] = 0


# ----------------------------------------------------------------- datagrams

def new_measurement() -> np.ndarray:
    """A zeroed measurement record (0-d structured array) with its size and id set."""
    rec = np.zeros((), dtype=MEASUREMENT_DTYPE)
    rec["head"]["packetSize"] = MEASUREMENT_SIZE
    rec["head"]["datagramId"] = MEASUREMENT_ID
    return rec


def new_command() -> np.ndarray:
    """A zeroed command record with its size and id set."""
    rec = np.zeros((), dtype=COMMAND_DTYPE)
    rec["head"]["packetSize"] = COMMAND_SIZE
    rec["head"]["datagramId"] = COMMAND_ID
    return rec


def _decode(data, dtype: np.dtype, size: int, datagram_id: int, what: str) -> np.ndarray:
    view = memoryview(data).cast("B")
    n = view.nbytes
    got_id = struct.unpack_from("<H", view, 6)[0] if n >= 8 else None
    if n != size:
        raise FriWireError(what, "size", n, got_id, (size, datagram_id))
    if got_id != datagram_id:
        raise FriWireError(what, "id", n, got_id, (size, datagram_id))
    # a record over a private copy of the bytes (copying a structured array with offsets is
    # 20x slower than copying its bytes)
    return np.ndarray((), dtype=dtype, buffer=bytearray(view))


def decode_measurement(data) -> np.ndarray:
    """A measurement datagram (any bytes-like) as a record (a copy); FriWireError if it is not one."""
    return _decode(data, MEASUREMENT_DTYPE, MEASUREMENT_SIZE, MEASUREMENT_ID, "measurement")


def decode_command(data) -> np.ndarray:
    """A command datagram (any bytes-like) as a record (a copy); FriWireError if it is not one."""
    return _decode(data, COMMAND_DTYPE, COMMAND_SIZE, COMMAND_ID, "command")


_DEFAULT_EXTRAS = MeasurementExtras()


def write_measurement(rec: np.ndarray, m: MeasurementPacket, *, krl: KrlChannels | None = None,
                      extras: MeasurementExtras | None = None) -> np.ndarray:
    """Fill measurement record ``rec`` (from :func:`new_measurement`) from ``m``; returns ``rec``."""
    x = _DEFAULT_EXTRAS if extras is None else extras
    head = rec["head"]
    head["sendSeqCount"] = counter16(m.seq)
    head["reflSeqCount"] = counter16(m.reflected_seq) if m.reflected_seq >= 0 else 0
    head["packetSize"] = MEASUREMENT_SIZE
    head["datagramId"] = MEASUREMENT_ID
    write_krl(rec, krl)
    intf = rec["intf"]
    intf["timestamp"] = m.stamp_ns * 1e-9
    intf["state"] = int(m.state)
    intf["quality"] = int(m.quality)
    intf["desiredMsrSampleTime"] = x.sample_time_s
    intf["desiredCmdSampleTime"] = x.sample_time_s
    intf["safetyLimits"] = x.safety_limits
    stat = intf["stat"]
    stat["answerRate"] = m.answer_rate
    stat["latency"] = m.latency_s
    stat["jitter"] = m.jitter_s
    stat["missRate"] = m.miss_rate
    stat["missCounter"] = x.miss_counter
    robot = rec["robot"]
    robot["power"] = x.power
    robot["control"] = int(m.control_mode)
    robot["error"] = x.error
    robot["warning"] = x.warning
    robot["temperature"] = 0.0 if x.temperature is None else x.temperature
    data = rec["data"]
    data["msrJntPos"] = m.msr_jnt_pos
    data["msrCartPos"] = m.msr_cart_pos
    data["cmdJntPos"] = m.msr_jnt_pos if x.cmd_jnt_pos is None else x.cmd_jnt_pos
    data["cmdJntPosFriOffset"] = 0.0 if x.cmd_jnt_pos_fri_offset is None else x.cmd_jnt_pos_fri_offset
    data["cmdCartPos"] = m.msr_cart_pos if x.cmd_cart_pos is None else x.cmd_cart_pos
    data["cmdCartPosFriOffset"] = 0.0 if x.cmd_cart_pos_fri_offset is None else x.cmd_cart_pos_fri_offset
    data["msrJntTrq"] = 0.0 if x.msr_jnt_trq is None else x.msr_jnt_trq
    data["estExtJntTrq"] = 0.0 if x.est_ext_jnt_trq is None else x.est_ext_jnt_trq
    data["estExtTcpFT"] = m.est_ext_tcp_ft  # FRI order on both sides
    data["jacobian"] = 0.0 if x.jacobian is None else x.jacobian
    data["massMatrix"] = 0.0 if x.mass_matrix is None else x.mass_matrix
    data["gravity"] = 0.0 if x.gravity is None else x.gravity
    return rec


def encode_measurement(m: MeasurementPacket, *, krl: KrlChannels | None = None,
                       extras: MeasurementExtras | None = None) -> bytes:
    """``m`` as the 916 bytes the KRC sends."""
    return write_measurement(new_measurement(), m, krl=krl, extras=extras).tobytes()


def measurement_packet(rec: np.ndarray, near: int | None = None) -> MeasurementPacket:
    """A decoded measurement as the testbench's packet (what a remote would read).

    ``seq`` is the header's counter unwrapped near ``near`` (the counter itself
    without one); ``reflected_seq`` is unwrapped near ``seq``.  Unknown state,
    quality or control values raise ValueError.
    """
    head, intf, data = rec["head"], rec["intf"], rec["data"]
    send = int(head["sendSeqCount"])
    seq = send if near is None else unwrap(send, near)
    stat = intf["stat"]
    return MeasurementPacket(
        seq=seq,
        reflected_seq=unwrap(int(head["reflSeqCount"]), seq),
        stamp_ns=round(float(intf["timestamp"]) * 1e9),
        state=FriState(int(intf["state"])),
        quality=FriQuality(int(intf["quality"])),
        control_mode=ControlMode(int(rec["robot"]["control"])),
        msr_jnt_pos=np.array(data["msrJntPos"], dtype=np.float64),
        msr_cart_pos=np.array(data["msrCartPos"], dtype=np.float64),
        est_ext_tcp_ft=np.array(data["estExtTcpFT"], dtype=np.float64),
        answer_rate=float(stat["answerRate"]),
        latency_s=float(stat["latency"]),
        jitter_s=float(stat["jitter"]),
        miss_rate=float(stat["missRate"]),
    )


def write_command(rec: np.ndarray, cmd: CommandPacket, *, send_seq: int, krl: KrlChannels | None = None,
                  flags: int | None = None) -> np.ndarray:
    """Fill command record ``rec`` (from :func:`new_command`) from ``cmd``, as a remote sends it.

    ``reflSeqCount`` is ``cmd.seq``'s counter, ``sendSeqCount`` the remote's own
    ``send_seq``'s.  ``flags`` default to the fields ``cmd`` holds for its
    ``requested_mode`` (CART_IMP: 0x3500; POSITION: jntPos; JNT_IMP: jntPos and the joint fields it holds).
    """
    head = rec["head"]
    head["sendSeqCount"] = counter16(send_seq)
    head["reflSeqCount"] = counter16(cmd.seq)
    head["packetSize"] = COMMAND_SIZE
    head["datagramId"] = COMMAND_ID
    write_krl(rec, krl)
    c = rec["cmd"]
    c["cmdFlags"] = _packet_flags(cmd) if flags is None else int(flags)
    c["jntPos"] = 0.0 if cmd.jnt_pos is None else cmd.jnt_pos
    c["cartPos"] = cmd.cart_pos
    c["addJntTrq"] = 0.0 if cmd.add_jnt_trq is None else cmd.add_jnt_trq
    c["addTcpFT"] = cmd.add_tcp_ft  # FRI order on both sides
    c["jntStiffness"] = 0.0 if cmd.jnt_stiffness is None else cmd.jnt_stiffness
    c["jntDamping"] = 0.0 if cmd.jnt_damping is None else cmd.jnt_damping
    c["cartStiffness"] = fri_order(cmd.cart_stiffness)
    c["cartDamping"] = fri_order(cmd.cart_damping)
    return rec


def encode_command(cmd: CommandPacket, *, send_seq: int, krl: KrlChannels | None = None,
                   flags: int | None = None) -> bytes:
    """``cmd`` as the 376 bytes a remote sends."""
    return write_command(new_command(), cmd, send_seq=send_seq, krl=krl, flags=flags).tobytes()


def command_packet(rec: np.ndarray, seq: int, current_mode: ControlMode,
                   defaults: CommandPacket | None = None) -> CommandPacket:
    """A decoded command as the testbench's packet answering cycle ``seq``.

    ``seq`` is the full cycle number (``unwrap(rec["head"]["reflSeqCount"], open
    cycle)``); ``requested_mode`` is :func:`mode_for_flags` of the flags against the
    KRC's ``current_mode``.  A field whose flag is not set is taken from ``defaults``
    (the KRC's own values: its held pose and stiffness); without defaults it is the
    wire's value.  Nothing is checked here: ``CommandPacket.is_valid`` judges it.
    """
    c = rec["cmd"]
    flags = int(c["cmdFlags"])

    def take(flag: CommandFlags, wire: np.ndarray, name: str):
        if flags & flag or defaults is None:
            return wire
        default = getattr(defaults, name)
        return None if default is None else np.array(default, dtype=np.float64)

    return CommandPacket(
        seq=int(seq),
        cart_pos=take(CommandFlags.CART_POS, np.array(c["cartPos"], dtype=np.float64), "cart_pos"),
        cart_stiffness=take(CommandFlags.CART_STIFF, fri_order(c["cartStiffness"]), "cart_stiffness"),
        cart_damping=take(CommandFlags.CART_DAMP, fri_order(c["cartDamping"]), "cart_damping"),
        add_tcp_ft=take(CommandFlags.TCP_FT, np.array(c["addTcpFT"], dtype=np.float64), "add_tcp_ft"),
        jnt_pos=take(CommandFlags.JNT_POS, np.array(c["jntPos"], dtype=np.float64), "jnt_pos"),
        requested_mode=mode_for_flags(flags, current_mode),
        # unflagged, the KRC's own joint impedance (None): KrcController's defaults
        jnt_stiffness=(np.array(c["jntStiffness"], dtype=np.float64) if flags & CommandFlags.JNT_STIFF else None),
        jnt_damping=np.array(c["jntDamping"], dtype=np.float64) if flags & CommandFlags.JNT_DAMP else None,
        add_jnt_trq=np.array(c["addJntTrq"], dtype=np.float64) if flags & CommandFlags.JNT_TRQ else None,
    )
