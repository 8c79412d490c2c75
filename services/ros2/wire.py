"""ROS 2's Zenoh wire (rmw_zenoh), as ros2/rmw_zenoh's ``docs/design.md`` writes it down for
other implementations, checked against its sources (``liveliness_utils.cpp``, ``qos.cpp``,
``attachment_helpers.cpp``, ``rmw_publisher_data.cpp``): the key a topic's data is put on,
the liveliness tokens by which ``ros2 node list`` and ``ros2 topic list`` find a node and
its publishers, the QoS written into a token, and the attachment every put carries.
Bytes and strings only; ``services.transport.lab.ros2_wire`` puts them on a session.

The format is the one of rmw_zenoh 0.2.4 and later on Jazzy, and of Kilted and Rolling
(the positional attachment arrived in 0.2.4; Jazzy 0.2.0-0.2.3 used labelled pairs and
cannot read these puts; Humble's 0.1.x has no type hashes at all).
"""

from __future__ import annotations

import struct

ADMIN_SPACE = "@ros2_lv"
# the cell as one ROS 2 node: /etar_cell in the root namespace
NODE_NAME, NAMESPACE = "etar_cell", "/"
FULL_NODE_NAME = NAMESPACE + NODE_NAME
DEFAULT_ENCLAVE = "/"  # rcl's
MAX_DOMAIN_ID = 232  # ROS 2's domain ids: 0..232 (REP 2005's range for DDS ports, kept by every RMW)

# QoS as rmw enumerates it; a token writes only what differs from rmw_zenoh's default
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST = 1
DEFAULT_DEPTH = 42


def check_domain(domain: int, name: str = "domain") -> int:
    if isinstance(domain, bool) or not isinstance(domain, int) or not 0 <= domain <= MAX_DOMAIN_ID:
        raise ValueError(f"{name}: a ROS 2 domain id is an integer in 0..{MAX_DOMAIN_ID}, got {domain!r}")
    return domain


def mangle(name: str) -> str:
    """A name inside a token: every '/' is '%' (so '/' is '%', '/ft_sensor/wrench' '%ft_sensor%wrench')."""
    return name.replace("/", "%")


def dds_type(msgtype: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_``."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def data_key(domain: int, topic: str, msgtype: str, type_hash: str) -> str:
    """The key a topic's messages are put on: ``<domain>/<topic>/<dds type>/<RIHS01 hash>``."""
    return f"{domain}/{topic.strip('/')}/{dds_type(msgtype)}/{type_hash}"


def qos_string(reliability: int = RELIABLE, durability: int = VOLATILE, depth: int = 10) -> str:
    """rmw_zenoh's ``qos_to_keyexpr`` for a KEEP_LAST publisher without deadline, lifespan or
    liveliness lease: ``<rel>:<dur>:<hist>,<depth>:<deadline>:<lifespan>:<liveliness>``, a field
    left empty where it is the default (RELIABLE, VOLATILE, KEEP_LAST, 42, infinite, AUTOMATIC)."""
    rel = "" if reliability == RELIABLE else str(reliability)
    dur = "" if durability == VOLATILE else str(durability)
    dep = "" if depth == DEFAULT_DEPTH else str(depth)
    return f"{rel}:{dur}:,{dep}:,:,:,,"


def node_token(domain: int, zid: str, node_id: int, namespace: str, node: str,
               enclave: str = DEFAULT_ENCLAVE) -> str:
    """The node's liveliness token (``NN``)."""
    return "/".join((ADMIN_SPACE, str(domain), zid, str(node_id), str(node_id), "NN", mangle(enclave),
                     mangle(namespace), node))


def publisher_token(domain: int, zid: str, node_id: int, entity_id: int, namespace: str, node: str, topic: str,
                    msgtype: str, type_hash: str, qos: str, enclave: str = DEFAULT_ENCLAVE) -> str:
    """A publisher's liveliness token (``MP``)."""
    return "/".join((ADMIN_SPACE, str(domain), zid, str(node_id), str(entity_id), "MP", mangle(enclave),
                     mangle(namespace), node, mangle(topic), dds_type(msgtype), type_hash, qos))


def gid(token: str) -> bytes:
    """The entity's 16-byte GID: XXH3-128 (seed 0) of its whole liveliness token, the low
    64 bits then the high, each little-endian (rmw_zenoh's ``Entity``)."""
    import xxhash

    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


def attachment(sequence_number: int, source_timestamp_ns: int, entity_gid: bytes) -> bytes:
    """What every put carries: int64 LE sequence number (from 1), int64 LE source timestamp
    (ns since the epoch), the GID's length as one byte, the GID."""
    return struct.pack("<qqB", sequence_number, source_timestamp_ns, len(entity_gid)) + entity_gid
