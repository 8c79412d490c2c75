"""rmw_zenoh's wire as ros2/rmw_zenoh's docs/design.md and its sources write it: keys,
liveliness tokens, QoS strings, the GID and the attachment; and the type hashes as rosbags
computes them (the judge of RIHS01), String's equal to the value in the design document."""

import struct

import pytest
import xxhash

from services.ros2 import types, wire

# docs/design.md (ros2/rmw_zenoh), its example of a std_msgs/msg/String topic
DESIGN_STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_the_hashes_are_rosbags_and_strings_is_the_design_documents():
    from rosbags.typesys import Stores, get_typestore

    jazzy = get_typestore(Stores.ROS2_JAZZY)
    for topic in types.TOPICS:
        if topic.type.startswith("etar_msgs/"):
            continue
        assert topic.hash == jazzy.hash_rihs01(topic.type), topic.name
    assert types.type_hash("std_msgs/msg/String") == DESIGN_STRING_HASH
    # the project's own type: a hash of its shipped .msg, 64 hex digits, and a change to the
    # file would change it (the field list is part of what is hashed)
    own = types.type_hash(types.PHASE_ESTIMATE)
    assert own.startswith("RIHS01_") and len(own) == 7 + 64
    from rosbags.typesys import get_types_from_msg

    other = get_typestore(Stores.ROS2_JAZZY)
    other.register(get_types_from_msg("std_msgs/Header header\nint32 phase\nfloat64[] posterior\n",
                                      types.PHASE_ESTIMATE))
    assert other.hash_rihs01(types.PHASE_ESTIMATE) != own


def test_keys_and_tokens_are_written_as_the_design_document_writes_them():
    # design.md: 0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...
    assert wire.data_key(0, "/chatter", "std_msgs/msg/String", DESIGN_STRING_HASH) == \
        f"0/chatter/std_msgs::msg::dds_::String_/{DESIGN_STRING_HASH}"
    assert wire.data_key(3, "/ft_sensor/wrench", "geometry_msgs/msg/WrenchStamped", "H") == \
        "3/ft_sensor/wrench/geometry_msgs::msg::dds_::WrenchStamped_/H"
    assert wire.node_token(0, "8b7ba6", 0, "/", "etar_cell") == "@ros2_lv/0/8b7ba6/0/0/NN/%/%/etar_cell"
    token = wire.publisher_token(0, "8b7ba6", 0, 10, "/", "etar_cell", "/ft_sensor/wrench",
                                 "geometry_msgs/msg/WrenchStamped", "H", wire.qos_string())
    assert token == ("@ros2_lv/0/8b7ba6/0/10/MP/%/%/etar_cell/%ft_sensor%wrench/"
                     "geometry_msgs::msg::dds_::WrenchStamped_/H/::,10:,:,:,,")


@pytest.mark.parametrize("qos, expected", [
    ((wire.RELIABLE, wire.VOLATILE, 10), "::,10:,:,:,,"),  # design.md's listener
    ((wire.RELIABLE, wire.TRANSIENT_LOCAL, 1), ":1:,1:,:,:,,"),
    ((wire.BEST_EFFORT, wire.VOLATILE, 5), "2::,5:,:,:,,"),
    ((wire.RELIABLE, wire.VOLATILE, wire.DEFAULT_DEPTH), "::,:,:,:,,"),
])
def test_a_qos_writes_only_what_differs_from_rmw_zenohs_default(qos, expected):
    assert wire.qos_string(*qos) == expected


def test_the_gid_is_xxh3_128_of_the_token_low_half_first_and_the_attachment_is_33_bytes():
    token = "@ros2_lv/0/8b7ba6/0/10/MP/%/%/etar_cell/%tf/tf2_msgs::msg::dds_::TFMessage_/H/::,100:,:,:,,"
    gid = wire.gid(token)
    digest = xxhash.xxh3_128_digest(token.encode())  # big-endian: high half first
    assert gid == digest[8:][::-1] + digest[:8][::-1]
    data = wire.attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(data) == 33
    assert struct.unpack_from("<qqB", data) == (7, 1_700_000_000_123_456_789, 16) and data[17:] == gid


@pytest.mark.parametrize("domain", [-1, 233, 1.0, True, "0"])
def test_a_domain_outside_ros_2s_range_is_refused_by_name(domain):
    with pytest.raises(ValueError, match=r"--ros2 DOMAIN: a ROS 2 domain id is an integer in 0..232"):
        wire.check_domain(domain, "--ros2 DOMAIN")
