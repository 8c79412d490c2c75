"""The FRI measurement and command as the bus carries them, converted one way each, here
only: a ``MeasurementPacket`` (the KRC's) or a measurement datagram (a remote's, over
UDP) to the ``robot/state`` message, and a ``robot/command`` message to what the KRC
judges (its numbers, or the ``CommandPacket`` they make).  The datagrams' own bytes are ``robot_sim.wire``'s."""

from __future__ import annotations

import numpy as np

from robot_sim.krc.krl import TB_EPISODE, TB_GRAVITY_COMPENSATION
from robot_sim.krc.link import FriLink
from robot_sim.krc.packets import CommandPacket, MeasurementPacket, control_mode_or_value
from robot_sim.wire.fri_datagrams import read_krl
from services.runtime.messages import ROBOT_STATE


def state_message(m: MeasurementPacket, *, sent_ns: int, safety: int, gravity_compensation: bool,
                  episode: int) -> tuple[bytes, dict]:
    """``robot/state`` (payload, message) for the KRC's measurement ``m``."""
    header = (m.reflected_seq, int(m.state), int(m.quality), int(m.control_mode), m.answer_rate, m.latency_s,
              m.jitter_s, m.miss_rate)
    return _state(m.seq, m.stamp_ns, header, m.msr_jnt_pos, m.msr_cart_pos, m.est_ext_tcp_ft, sent_ns, safety,
                  gravity_compensation, episode)


def measured_state(link: FriLink, seq: int, stamp_ns: int, msr_jnt_pos, msr_cart_pos, est_ext_tcp_ft, *,
                   sent_ns: int, safety: int, gravity_compensation: bool, episode: int) -> tuple[bytes, dict]:
    """``robot/state`` for the cycle the KRC opened without a packet (``RobotCell.measure``):
    the packet's numbers as given, the rest from the link's ``sent_header``: what
    ``state_message`` of the packet gives."""
    return _state(seq, stamp_ns, link.sent_header(), msr_jnt_pos, msr_cart_pos, est_ext_tcp_ft, sent_ns, safety,
                  gravity_compensation, episode)


def _state(seq, stamp_ns, header, q, x, ft, sent_ns, safety, gravity_compensation, episode) -> tuple[bytes, dict]:
    reflected_seq, state, quality, mode, answer_rate, latency_s, jitter_s, miss_rate = header
    return ROBOT_STATE.pack(
        seq=seq, stamp_ns=stamp_ns, sent_ns=sent_ns, reflected_seq=reflected_seq, fri_state=state, fri_quality=quality,
        control_mode=mode, msr_jnt_pos=q, msr_cart_pos=x, est_ext_tcp_ft=ft, answer_rate=answer_rate,
        latency_s=latency_s, jitter_s=jitter_s, miss_rate=miss_rate, safety=safety,
        gravity_compensation=gravity_compensation, episode=episode)


def state_from_datagram(rec, *, seq: int, stamp_ns: int, reflected_seq: int, sent_ns: int) -> tuple[bytes, dict]:
    """``robot/state`` (payload, message) for a decoded measurement datagram ``rec``, whose
    16-bit counters the caller has unwrapped to ``seq`` and ``reflected_seq`` and whose time
    it has rounded to its cycle (``stamp_ns``): the episode and gravity compensation from
    the testbench's KRL channels, the KRC's error as ``safety``."""
    intf, stat, data = rec["intf"], rec["intf"]["stat"], rec["data"]
    krl = read_krl(rec)
    m = MeasurementPacket(
        seq=seq, reflected_seq=reflected_seq, stamp_ns=stamp_ns, state=int(intf["state"]),
        quality=int(intf["quality"]), control_mode=int(rec["robot"]["control"]),
        msr_jnt_pos=np.asarray(data["msrJntPos"], dtype=np.float64),
        msr_cart_pos=np.asarray(data["msrCartPos"], dtype=np.float64),
        est_ext_tcp_ft=np.asarray(data["estExtTcpFT"], dtype=np.float64),
        answer_rate=float(stat["answerRate"]), latency_s=float(stat["latency"]), jitter_s=float(stat["jitter"]),
        miss_rate=float(stat["missRate"]))
    return state_message(m, sent_ns=sent_ns, safety=int(rec["robot"]["error"]),
                         gravity_compensation=krl.flag(TB_GRAVITY_COMPENSATION), episode=int(krl.ints[TB_EPISODE - 1]))


def deliver_command(link: FriLink, msg: dict, t_sent_ns: int) -> bool:
    """A ``robot/command`` message to the KRC's FRI link, sent at ``t_sent_ns``: its numbers
    straight to where the link checks and keeps them (``FriLink.receive_fields``), or,
    through the link's faults (which copy, corrupt and hold back packets), as the packet
    ``command_packet`` makes.  Whether it was accepted as its cycle's answer."""
    if link.faults is not None:
        return link.deliver(command_packet(msg), t_sent_ns, owned=True)
    return link.receive_fields(msg["seq"], msg["requested_mode"], msg["cart_pos"], msg["cart_stiffness"],
                               msg["cart_damping"], msg["add_tcp_ft"], t_sent_ns)


def command_packet(msg: dict) -> CommandPacket:
    """The KRC's packet for a ``robot/command`` message, made from the message's lists in
    float64 as the link's own copy would be (the link may keep it without copying)."""
    return CommandPacket(seq=msg["seq"], cart_pos=np.array(msg["cart_pos"], dtype=np.float64),
                         cart_stiffness=np.array(msg["cart_stiffness"], dtype=np.float64),
                         cart_damping=np.array(msg["cart_damping"], dtype=np.float64),
                         add_tcp_ft=np.array(msg["add_tcp_ft"], dtype=np.float64),
                         requested_mode=control_mode_or_value(msg["requested_mode"]))
