"""The FRI 1.0 datagrams byte for byte: every field at WIRE.md's offset, read back with
``struct`` (not with the codec's own dtype), sizes, round trips, counters and errors."""

import itertools
import struct

import numpy as np
import pytest

from robot_sim.krc.packets import (CommandPacket, ControlMode, FriQuality, FriState, MeasurementExtras,
                                   MeasurementPacket, fri_order)
from robot_sim.krc.krl import KrlChannels
from robot_sim.wire.fri_datagrams import (COMMAND_DTYPE, COMMAND_ID, COMMAND_SIZE, CommandFlags, FriWireError,
                                          MEASUREMENT_DTYPE, MEASUREMENT_ID, MEASUREMENT_SIZE, command_packet,
                                          counter16, decode_command, decode_measurement, encode_command,
                                          encode_measurement, field_offsets, measurement_packet,
                                          mode_for_flags, new_command, new_measurement, unwrap)

# WIRE.md's tables, written out: (field, byte offset, struct format of one value, count)
HEAD_KRL = [
    ("head.sendSeqCount", 0, "H", 1), ("head.reflSeqCount", 2, "H", 1), ("head.packetSize", 4, "H", 1),
    ("head.datagramId", 6, "H", 1), ("krl.realData", 8, "f", 16), ("krl.intData", 72, "i", 16),
    ("krl.boolData", 136, "H", 1), ("krl.fill", 138, "H", 1),
]
MEASUREMENT_FIELDS = HEAD_KRL + [
    ("intf.timestamp", 140, "f", 1), ("intf.state", 144, "H", 1), ("intf.quality", 146, "H", 1),
    ("intf.desiredMsrSampleTime", 148, "f", 1), ("intf.desiredCmdSampleTime", 152, "f", 1),
    ("intf.safetyLimits", 156, "f", 1), ("intf.stat.answerRate", 160, "f", 1), ("intf.stat.latency", 164, "f", 1),
    ("intf.stat.jitter", 168, "f", 1), ("intf.stat.missRate", 172, "f", 1), ("intf.stat.missCounter", 176, "I", 1),
    ("robot.power", 180, "H", 1), ("robot.control", 182, "H", 1), ("robot.error", 184, "H", 1),
    ("robot.warning", 186, "H", 1), ("robot.temperature", 188, "f", 7),
    ("data.msrJntPos", 216, "f", 7), ("data.msrCartPos", 244, "f", 12), ("data.cmdJntPos", 292, "f", 7),
    ("data.cmdJntPosFriOffset", 320, "f", 7), ("data.cmdCartPos", 348, "f", 12),
    ("data.cmdCartPosFriOffset", 396, "f", 12), ("data.msrJntTrq", 444, "f", 7), ("data.estExtJntTrq", 472, "f", 7),
    ("data.estExtTcpFT", 500, "f", 6), ("data.jacobian", 524, "f", 42), ("data.massMatrix", 692, "f", 49),
    ("data.gravity", 888, "f", 7),
]
COMMAND_FIELDS = HEAD_KRL + [
    ("cmd.cmdFlags", 140, "I", 1), ("cmd.jntPos", 144, "f", 7), ("cmd.cartPos", 172, "f", 12),
    ("cmd.addJntTrq", 220, "f", 7), ("cmd.addTcpFT", 248, "f", 6), ("cmd.jntStiffness", 272, "f", 7),
    ("cmd.jntDamping", 300, "f", 7), ("cmd.cartStiffness", 328, "f", 6), ("cmd.cartDamping", 352, "f", 6),
]

# a valid pose (a rotation about z by 90 degrees) and values exact in float32
POSE = np.array([0.0, -1.0, 0.0, 0.25, 1.0, 0.0, 0.0, -0.5, 0.0, 0.0, 1.0, 0.75])
Q = np.array([0.125, -0.25, 0.375, -0.5, 0.625, -0.75, 0.875])
FT = np.array([1.5, -2.5, 3.5, 0.25, -0.125, 0.0625])  # Fx Fy Fz Tz Ty Tx


def at(data: bytes, fmt: str, offset: int, count: int):
    values = struct.unpack_from(f"<{count}{fmt}", data, offset)
    return values[0] if count == 1 else list(values)


def path(rec: np.ndarray, name: str):
    parent = rec
    *parents, leaf = name.split(".")
    for p in parents:
        parent = parent[p]
    return parent, leaf


def distinct_values(fields):
    """Each field its own values: field k's element i is 1000 k + i + 1 (a small integer,
    exact in float32, distinct across the datagram)."""
    return {name: [1000 * k + i + 1 for i in range(count)] for k, (name, _, _, count) in enumerate(fields)}


@pytest.mark.parametrize("dtype, fields, size", [(MEASUREMENT_DTYPE, MEASUREMENT_FIELDS, MEASUREMENT_SIZE),
                                                 (COMMAND_DTYPE, COMMAND_FIELDS, COMMAND_SIZE)],
                         ids=["measurement", "command"])
def test_every_field_sits_at_its_wire_md_offset(dtype, fields, size):
    assert dtype.itemsize == size
    # the codec has exactly WIRE.md's fields, and they tile the datagram without a gap
    assert sorted(field_offsets(dtype)) == sorted(name for name, *_ in fields)
    covered = sorted((off, off + struct.calcsize(f"<{n}{fmt}")) for _, off, fmt, n in fields)
    assert covered[0][0] == 0 and covered[-1][1] == size
    assert all(a[1] == b[0] for a, b in itertools.pairwise(covered))

    rec = np.zeros((), dtype=dtype)
    values = distinct_values(fields)
    for name, *_ in fields:
        parent, leaf = path(rec, name)
        parent[leaf] = np.reshape(values[name], parent[leaf].shape)
    data = rec.tobytes()
    assert len(data) == size
    for name, offset, fmt, count in fields:
        got = at(data, fmt, offset, count)
        assert got == (values[name][0] if count == 1 else values[name]), name


def test_sizes_and_ids_of_encoded_datagrams():
    m = measurement()
    data = encode_measurement(m)
    assert len(data) == 916
    assert struct.unpack_from("<4H", data, 0) == (m.seq, m.reflected_seq, 916, 0x2006)
    cmd = CommandPacket.from_measurement(m)
    data = encode_command(cmd, send_seq=9)
    assert len(data) == 376
    assert struct.unpack_from("<4H", data, 0) == (9, m.seq, 376, 0x1005)
    assert (MEASUREMENT_ID, COMMAND_ID) == (0x2006, 0x1005)
    assert new_measurement()["head"]["packetSize"] == 916 and new_command()["head"]["datagramId"] == 0x1005


def measurement(seq=7, reflected=6, **kw) -> MeasurementPacket:
    values = {"seq": seq, "reflected_seq": reflected, "stamp_ns": 1_250_000_000, "state": FriState.CMD,
              "quality": FriQuality.OK, "control_mode": ControlMode.CART_IMP, "msr_jnt_pos": Q.copy(),
              "msr_cart_pos": POSE.copy(), "est_ext_tcp_ft": FT.copy(), "answer_rate": 0.96875,
              "latency_s": 0.000125, "jitter_s": 0.0000625, "miss_rate": 0.03125}
    return MeasurementPacket(**(values | kw))


def test_a_measurement_packet_goes_where_fri_reads_it():
    krl = KrlChannels(reals=np.arange(16) + 0.5, ints=np.arange(16) * -3, bools=0)
    krl.set_flag(1, True)
    krl.set_flag(16, True)
    extras = MeasurementExtras(
        cmd_jnt_pos=Q + 1, cmd_jnt_pos_fri_offset=Q + 2, cmd_cart_pos=POSE + 3, cmd_cart_pos_fri_offset=POSE + 4,
        msr_jnt_trq=Q + 5, est_ext_jnt_trq=Q + 6, jacobian=np.arange(42.0).reshape(6, 7),
        mass_matrix=np.arange(49.0).reshape(7, 7) + 100, gravity=Q + 7, temperature=Q + 30, miss_counter=17,
        sample_time_s=0.002, safety_limits=0.5, power=0x7F, error=3, warning=4)
    data = encode_measurement(measurement(), krl=krl, extras=extras)
    assert at(data, "f", 8, 16) == (np.arange(16) + 0.5).tolist()  # $FRI_TO_REA[1..16]
    assert at(data, "i", 72, 16) == (np.arange(16) * -3).tolist()  # $FRI_TO_INT
    assert at(data, "H", 136, 1) == 0x8001  # $FRI_TO_BOOL[1] is bit 0, [16] bit 15
    assert at(data, "f", 140, 1) == 1.25
    assert (at(data, "H", 144, 1), at(data, "H", 146, 1)) == (2, 2)  # CMD, OK
    assert at(data, "f", 148, 1) == np.float32(0.002) and at(data, "f", 152, 1) == np.float32(0.002)
    assert at(data, "f", 156, 1) == 0.5
    assert [at(data, "f", o, 1) for o in (160, 164, 168, 172)] == \
        [0.96875, np.float32(0.000125), np.float32(0.0000625), 0.03125]
    assert at(data, "I", 176, 1) == 17
    assert [at(data, "H", o, 1) for o in (180, 182, 184, 186)] == [0x7F, 2, 3, 4]
    assert at(data, "f", 188, 7) == (Q + 30).tolist()
    assert at(data, "f", 216, 7) == Q.tolist()
    assert at(data, "f", 244, 12) == POSE.tolist()
    assert at(data, "f", 292, 7) == (Q + 1).tolist()
    assert at(data, "f", 320, 7) == (Q + 2).tolist()
    assert at(data, "f", 348, 12) == (POSE + 3).tolist()
    assert at(data, "f", 396, 12) == (POSE + 4).tolist()
    assert at(data, "f", 444, 7) == (Q + 5).tolist()
    assert at(data, "f", 472, 7) == (Q + 6).tolist()
    assert at(data, "f", 500, 6) == FT.tolist()  # FRI order on both sides: Fx Fy Fz Tz Ty Tx
    assert at(data, "f", 524, 42) == np.arange(42.0).tolist()  # row-major 6x7
    assert at(data, "f", 692, 49) == (np.arange(49.0) + 100).tolist()
    assert at(data, "f", 888, 7) == (Q + 7).tolist()


def test_without_extras_the_commanded_values_mirror_the_measured_ones():
    data = encode_measurement(measurement())
    assert at(data, "f", 292, 7) == Q.tolist()  # cmdJntPos
    assert at(data, "f", 348, 12) == POSE.tolist()  # cmdCartPos: non-zero, consistent
    assert at(data, "f", 320, 7) == [0.0] * 7 and at(data, "f", 396, 12) == [0.0] * 12
    assert at(data, "H", 180, 1) != 0  # power: the Stanford library's IsMachineOK wants it
    assert at(data, "f", 148, 1) == np.float32(0.001)


def test_a_command_packet_goes_where_fri_reads_it_with_stiffness_and_damping_in_abc_order():
    stiffness = np.array([100.0, 200.0, 300.0, 10.0, 20.0, 30.0])  # x y z rx ry rz (the law's order)
    damping = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    cmd = CommandPacket(seq=7, cart_pos=POSE, cart_stiffness=stiffness, cart_damping=damping, add_tcp_ft=FT,
                        jnt_pos=Q)
    krl = KrlChannels()
    krl.ints[14], krl.ints[15] = 20, 10  # $FRI_FRM_INT[15] strategy, [16] request (Stanford)
    data = encode_command(cmd, send_seq=65539, krl=krl)
    assert struct.unpack_from("<4H", data, 0) == (3, 7, 376, 0x1005)
    assert at(data, "i", 72 + 14 * 4, 2) == [20, 10]
    assert at(data, "I", 140, 1) == 0x3500
    assert at(data, "f", 144, 7) == Q.tolist()
    assert at(data, "f", 172, 12) == POSE.tolist()
    assert at(data, "f", 248, 6) == FT.tolist()
    assert at(data, "f", 328, 6) == [100.0, 200.0, 300.0, 30.0, 20.0, 10.0]  # x y z A(z) B(y) C(x)
    assert at(data, "f", 352, 6) == pytest.approx([0.1, 0.2, 0.3, 0.6, 0.5, 0.4])
    assert at(data, "f", 220, 7) == [0.0] * 7  # no joint torque, stiffness, damping in a CommandPacket


def test_measurement_round_trip():
    m = measurement(seq=70_000, reflected=69_999)
    back = measurement_packet(decode_measurement(encode_measurement(m)), near=70_001)
    assert (back.seq, back.reflected_seq, back.stamp_ns) == (70_000, 69_999, m.stamp_ns)
    assert (back.state, back.quality, back.control_mode) == (m.state, m.quality, m.control_mode)
    for name in ("msr_jnt_pos", "msr_cart_pos", "est_ext_tcp_ft"):
        np.testing.assert_array_equal(getattr(back, name), getattr(m, name), err_msg=name)
    for name in ("answer_rate", "latency_s", "jitter_s", "miss_rate"):
        assert getattr(back, name) == pytest.approx(getattr(m, name), rel=1e-7), name


def test_nothing_reflected_yet_goes_out_as_zero():
    data = encode_measurement(measurement(seq=1, reflected=-1))
    assert at(data, "H", 2, 1) == 0


def test_command_round_trip():
    stiffness = np.array([1000.0, 2000.0, 3000.0, 50.0, 100.0, 150.0])
    damping = np.array([0.5, 0.625, 0.75, 0.875, 1.0, 0.25])
    cmd = CommandPacket(seq=65_540, cart_pos=POSE, cart_stiffness=stiffness, cart_damping=damping,
                        add_tcp_ft=FT, jnt_pos=Q)
    rec = decode_command(encode_command(cmd, send_seq=1))
    back = command_packet(rec, unwrap(int(rec["head"]["reflSeqCount"]), 65_541), ControlMode.CART_IMP)
    assert back.seq == 65_540 and back.requested_mode == ControlMode.CART_IMP
    for name in ("cart_pos", "cart_stiffness", "cart_damping", "add_tcp_ft", "jnt_pos"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cmd, name), err_msg=name)
    assert back.is_valid() == (True, "")


def test_unflagged_fields_come_from_the_defaults():
    m = measurement()
    defaults = CommandPacket.from_measurement(m, cart_stiffness=[2000.0] * 3 + [150.0] * 3)
    sent = CommandPacket.from_measurement(m, cart_stiffness=[1.0] * 6, cart_damping=[0.25] * 6,
                                          add_tcp_ft=[9.0] * 6)
    sent.cart_pos = POSE.copy()
    sent.cart_pos[3] += 0.125
    rec = decode_command(encode_command(sent, send_seq=1, flags=CommandFlags.CART_POS | CommandFlags.CART_DAMP))
    back = command_packet(rec, 7, ControlMode.CART_IMP, defaults)
    np.testing.assert_array_equal(back.cart_pos, sent.cart_pos)  # flagged: the wire's
    np.testing.assert_array_equal(back.cart_damping, [0.25] * 6)
    np.testing.assert_array_equal(back.cart_stiffness, defaults.cart_stiffness)  # not flagged: the defaults'
    np.testing.assert_array_equal(back.add_tcp_ft, defaults.add_tcp_ft)
    np.testing.assert_array_equal(back.jnt_pos, defaults.jnt_pos)


def test_command_flags_and_modes():
    assert CommandFlags.CART_IMP == 0x3500 and CommandFlags.JNT_IMP == 0x0035 and CommandFlags.POSITION == 0x0001
    assert [int(f) for f in (CommandFlags.JNT_POS, CommandFlags.JNT_TRQ, CommandFlags.JNT_STIFF, CommandFlags.JNT_DAMP,
                             CommandFlags.CART_POS, CommandFlags.TCP_FT, CommandFlags.CART_STIFF,
                             CommandFlags.CART_DAMP)] == [1, 4, 0x10, 0x20, 0x100, 0x400, 0x1000, 0x2000]
    cart = ControlMode.CART_IMP
    assert mode_for_flags(0x3500, cart) == cart
    assert mode_for_flags(CommandFlags.CART_POS, cart) == cart  # a subset fits
    assert mode_for_flags(0, ControlMode.JNT_IMP) == ControlMode.JNT_IMP  # nothing flagged fits any mode
    assert mode_for_flags(0x0001, ControlMode.JNT_IMP) == ControlMode.JNT_IMP  # the KRC's mode first
    assert mode_for_flags(0x0001, cart) == ControlMode.POSITION  # a mismatch the FriLink counts
    assert mode_for_flags(0x0035, cart) == ControlMode.JNT_IMP
    assert mode_for_flags(0x0101, cart) == ControlMode.OTHER  # joint and Cartesian fields mixed
    assert mode_for_flags(0x0002, cart) == ControlMode.OTHER  # a velocity: FRI 1.0 has none
    m = measurement()
    for mode, flags in ((ControlMode.POSITION, 0x0001), (ControlMode.JNT_IMP, 0x0001), (cart, 0x3500)):
        data = encode_command(CommandPacket.from_measurement(m, requested_mode=mode), send_seq=1)
        assert at(data, "I", 140, 1) == flags
        assert command_packet(decode_command(data), 7, mode).requested_mode == mode


def test_counters_wrap_and_unwrap_near_the_open_cycle():
    assert counter16(65_535) == 65_535 and counter16(65_536) == 0 and counter16(65_537) == 1
    assert unwrap(65_535, near=65_536) == 65_535  # the answer to the cycle before the wrap
    assert unwrap(0, near=65_536) == 65_536
    assert unwrap(0, near=65_535) == 65_536  # one ahead of the open cycle: not sent yet
    assert unwrap(65_534, near=131_073) == 131_070
    assert unwrap(5, near=5) == 5 and unwrap(3, near=0) == 3
    for near in (0, 1, 40_000, 65_535, 65_536, 10**9):
        for back in (0, 1, 2, 100, 32_768):
            assert unwrap(counter16(near - back), near) == near - back
        for ahead in (1, 32_767):
            assert unwrap(counter16(near + ahead), near) == near + ahead
    with pytest.raises(ValueError):
        unwrap(65_536, near=0)
    # a measurement past the wrap carries the low 16 bits, and a remote's echo of it comes back whole
    data = encode_measurement(measurement(seq=65_537, reflected=65_535))
    assert struct.unpack_from("<2H", data, 0) == (1, 65_535)
    cmd = encode_command(CommandPacket.from_measurement(measurement(seq=65_537)), send_seq=0)
    assert unwrap(struct.unpack_from("<H", cmd, 2)[0], near=65_537) == 65_537


@pytest.mark.parametrize("decode, good", [(decode_measurement, lambda: encode_measurement(measurement())),
                                          (decode_command, lambda: encode_command(
                                              CommandPacket.from_measurement(measurement()), send_seq=1))],
                         ids=["measurement", "command"])
def test_a_datagram_of_the_wrong_size_or_id_is_a_clear_error(decode, good):
    data = good()
    decode(data)
    decode(bytearray(data))
    decode(memoryview(data))
    for bad in (data[:-1], data + b"\0", b"", b"\x01\x02"):
        with pytest.raises(FriWireError, match="bytes, expected") as info:
            decode(bad)
        assert isinstance(info.value, ValueError) and info.value.reason == "size"
    wrong_id = bytearray(data)
    struct.pack_into("<H", wrong_id, 6, 0x1234)
    with pytest.raises(FriWireError, match="datagramId 0x1234") as info:
        decode(bytes(wrong_id))
    assert info.value.reason == "id" and info.value.datagram_id == 0x1234
    # each kind is the other's wrong size
    other = decode_command if decode is decode_measurement else decode_measurement
    with pytest.raises(FriWireError):
        other(data)


def test_decoding_copies():
    data = bytearray(encode_measurement(measurement()))
    rec = decode_measurement(data)
    data[216:220] = b"\0\0\0\0"
    assert rec["data"]["msrJntPos"][0] == Q[0]
    rec["data"]["msrJntPos"][1] = 5.0  # writable


def test_krl_channels_count_from_one():
    krl = KrlChannels()
    krl.set_flag(3, True)
    assert krl.bools == 0b100 and krl.flag(3) and not krl.flag(2)
    krl.set_flag(3, False)
    assert krl.bools == 0
    with pytest.raises(ValueError):
        krl.flag(0)
    with pytest.raises(ValueError):
        krl.set_flag(17, True)
    too_big = KrlChannels(ints=np.full(16, 1 << 31))
    with pytest.raises(ValueError, match="int32"):
        encode_measurement(measurement(), krl=too_big)


def test_orders_are_their_own_inverse():
    v = np.arange(6.0)
    np.testing.assert_array_equal(fri_order(v), [0, 1, 2, 5, 4, 3])
    np.testing.assert_array_equal(fri_order(fri_order(v)), v)
    J = np.arange(42.0).reshape(6, 7)
    np.testing.assert_array_equal(fri_order(J)[3], J[5])  # RZ row is the wz row
    np.testing.assert_array_equal(fri_order(fri_order(J)), J)
