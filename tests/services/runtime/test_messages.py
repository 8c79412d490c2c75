"""``MessageType.pack``: the bytes and the message they decode to, exactly, types included
(what the in-process bus hands over instead of decoding), and the same errors as before."""

import numpy as np
import pytest

from services.transport.inproc import _same
from services.runtime.messages import EPISODE_SUMMARY, MESSAGES, ROBOT_COMMAND, ROBOT_STATE, MessageError


def test_pack_gives_what_decoding_its_bytes_gives_for_numpy_inputs(rng):
    raw, msg = ROBOT_STATE.pack(
        seq=np.int64(7), stamp_ns=7_000_000, sent_ns=12, reflected_seq=-1, fri_state=2, fri_quality=3,
        control_mode=2, msr_jnt_pos=rng.normal(size=7), msr_cart_pos=tuple(rng.normal(size=12).tolist()),
        est_ext_tcp_ft=rng.normal(size=6) * 1e-300, answer_rate=np.float64(0.99), latency_s=1e-4, jitter_s=0.0,
        miss_rate=0.01, safety=0, gravity_compensation=np.bool_(False), episode=3)
    assert _same(ROBOT_STATE.decode(raw), msg)
    assert type(msg["seq"]) is int and type(msg["msr_cart_pos"]) is list and type(msg["gravity_compensation"]) is bool
    raw, msg = ROBOT_COMMAND.pack(seq=1, stamp_ns=0, sent_ns=0, cart_pos=np.eye(3, 4).ravel(), cart_stiffness=[0.0] * 6,
                                  cart_damping=[0.7] * 6, add_tcp_ft=-0.0 * np.ones(6), requested_mode=2, phase=-1,
                                  estimate_seq=-1, goal_reached=False, hold="", episode=0)
    assert _same(ROBOT_COMMAND.decode(raw), msg)


def test_every_message_type_has_a_pack_with_the_general_contract():
    for mtype in MESSAGES.values():
        with pytest.raises(MessageError, match="field 'seq' is missing"):
            mtype.pack(stamp_ns=0)
    with pytest.raises(MessageError, match=r"unknown field\(s\) \['bogus'\]"):
        ROBOT_COMMAND.pack(seq=1, stamp_ns=0, sent_ns=0, cart_pos=[0.0] * 12, cart_stiffness=[0.0] * 6,
                           cart_damping=[0.7] * 6, add_tcp_ft=[0.0] * 6, requested_mode=2, phase=-1, estimate_seq=-1,
                           goal_reached=False, hold="", episode=0, bogus=1)
    with pytest.raises(MessageError, match=r"non-finite value in field\(s\) \['add_tcp_ft'\]"):
        ROBOT_COMMAND.pack(seq=1, stamp_ns=0, sent_ns=0, cart_pos=[0.0] * 12, cart_stiffness=[0.0] * 6,
                           cart_damping=[0.7] * 6, add_tcp_ft=np.array([np.inf, 0, 0, 0, 0, 0]), requested_mode=2,
                           phase=-1, estimate_seq=-1, goal_reached=False, hold="", episode=0)
    # a type with optional fields keeps the general path: an optional field may be left out
    raw, msg = EPISODE_SUMMARY.pack(seq=1, stamp_ns=0, sent_ns=0, episode=0, kind="reproduction", reason="elapsed",
                                    first_seq=1, last_seq=2, sim_seconds=0.002, wall_seconds=0.01,
                                    final_position=[0.5, 0.0, 0.3], peak_contact_force=0.0, safety=0,
                                    missed_answers=0, fri={}, loop={})
    assert "goal_reached_at_s" not in msg and _same(EPISODE_SUMMARY.decode(raw), msg)
