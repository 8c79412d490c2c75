"""The ROS 2 side of the cell: which topics a ROS 2 machine sees, their message types,
QoS and type hashes, and the CDR that carries them.

The types are ROS 2 Jazzy's, as ``rosbags`` carries them (its type store holds the
standard message definitions; it computes RIHS01, REP 2011, and writes and reads CDR:
no CDR here is written by hand).  The one type of the project's own,
``etar_msgs/msg/PhaseEstimate``, is the ``.msg`` file shipped beside this module
(``etar_msgs/msg/PhaseEstimate.msg``), registered from its text, so its hash is computed
from what a ROS 2 workspace would build from the same file.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

PHASE_ESTIMATE = "etar_msgs/msg/PhaseEstimate"
PHASE_ESTIMATE_MSG = Path(__file__).parent / "etar_msgs" / "msg" / "PhaseEstimate.msg"


@dataclass(frozen=True)
class RosTopic:
    name: str  # as ROS 2 names it, with its leading '/'
    type: str  # pkg/msg/Type
    rate: str  # the Ros2Rates field that sets how often it is published ("": once, at the start)
    transient_local: bool = False  # kept for late subscribers (the description)
    depth: int = 10  # KEEP_LAST depth

    @property
    def hash(self) -> str:
        return type_hash(self.type)


# what a lab's tools look for (sensor_msgs/JointState on /joint_states, the URDF on
# /robot_description, transient local, an F/T sensor's WrenchStamped, /clock for use_sim_time)
TOPICS = (
    RosTopic("/robot_description", "std_msgs/msg/String", "", transient_local=True, depth=1),
    RosTopic("/clock", "rosgraph_msgs/msg/Clock", "clock_rate_hz"),
    RosTopic("/joint_states", "sensor_msgs/msg/JointState", "state_rate_hz"),
    RosTopic("/tf", "tf2_msgs/msg/TFMessage", "state_rate_hz", depth=100),
    RosTopic("/tcp_pose", "geometry_msgs/msg/PoseStamped", "state_rate_hz"),
    RosTopic("/ft_sensor/wrench", "geometry_msgs/msg/WrenchStamped", "wrench_rate_hz"),
    RosTopic("/etar/phase", PHASE_ESTIMATE, ""),
)
BY_NAME = {t.name: t for t in TOPICS}


@lru_cache(maxsize=None)
def typestore():
    """ROS 2 Jazzy's message types and the project's own."""
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg

    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(PHASE_ESTIMATE_MSG.read_text(), PHASE_ESTIMATE))
    return store


@lru_cache(maxsize=None)
def type_hash(msgtype: str) -> str:
    """The type's RIHS01 hash (``RIHS01_<64 hex digits>``)."""
    return typestore().hash_rihs01(msgtype)


def message_definition(msgtype: str) -> str:
    """The type's definition as rosbag2 writes it into a ``ros2msg`` schema: its own text,
    then each type it uses, after a line of '='."""
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return text


def to_cdr(message, msgtype: str) -> bytes:
    """CDR (little-endian XCDR1) after its 4-byte encapsulation header, as rmw_zenoh and
    rosbag2 carry it."""
    return bytes(typestore().serialize_cdr(message, msgtype))


def from_cdr(data: bytes, msgtype: str):
    return typestore().deserialize_cdr(data, msgtype)


def make(msgtype: str, **fields):
    """A message of ``msgtype`` from its fields."""
    return typestore().types[msgtype](**fields)
