"""``etar-bench export RUN_DIR --rosbag2``: a ROS 2 bag of each recording of a run, which
``ros2 bag info``/``play``, rosbags, Foxglove and PlotJuggler open.

Each recording (one episode) becomes one rosbag2 folder, ``OUT/<recording's name>/``, holding
``metadata.yaml`` and one MCAP file of the ``ros2`` profile: CDR messages, ``ros2msg``
schemas, and per channel the ``offered_qos_profiles`` and ``topic_type_hash`` that rosbag2's
own MCAP storage writes.  The topics are those of the live ``ros2`` node
(``services.ros2.types.TOPICS``), made by the same converter from the recording's messages
in the order the recorder received them; ``/robot_description`` comes first, from the world
of the scenario the recording carries.  A message's time in the bag is its simulated time
(``stamp_ns``), so ``ros2 bag play`` replays the episode at the pace it was simulated and
agrees with ``/clock``.

rosbags writes the bag (folder, metadata.yaml, MCAP); its MCAP storage leaves out the
``topic_type_hash`` channel metadata, so the MCAP file is then written once more with the
mcap library's writer, every record kept and the hash added.  The native recordings are
left as they are.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from services.foxglove.export import world_of_episode
from services.recordings.format import RecordingError
from services.recordings.reader import read_episode
from services.ros2 import BAGS_DIR
from services.ros2.convert import Ros2Rates, RosView
from services.ros2.types import BY_NAME, TOPICS, to_cdr, type_hash, typestore
from services.runtime.messages import BY_TOPIC, MessageError


@dataclass(frozen=True)
class Bagged:
    recording: Path
    bag: Path | None  # None: no bag made
    messages: int
    why: str

    def describe(self) -> str:
        return f"{self.recording}: {self.why}"


def qos_profiles(topic) -> list:
    """The QoS the live node offers on ``topic`` (``services.ros2.types.RosTopic``), as rosbags
    states it (reliable, keep last ``depth``, volatile or transient local)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    infinite = QosTime(9223372036, 854775807)
    return [Qos(QosHistory.KEEP_LAST, topic.depth, QosReliability.RELIABLE,
                QosDurability.TRANSIENT_LOCAL if topic.transient_local else QosDurability.VOLATILE,
                infinite, infinite, QosLiveliness.AUTOMATIC, infinite, False)]


def bag_of_recording(path, out_dir, rates: Ros2Rates = Ros2Rates(), views: dict | None = None) -> Bagged:
    """The bag of the recording at ``path``, written to ``out_dir/<its name>/`` (replaced if there)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = Path(path)
    episode = read_episode(path)
    if not episode.complete:
        return Bagged(path, None, 0, f"truncated ({episode.problem}): no bag; `etar-bench recover` it first")
    world = world_of_episode(episode, path)
    views = {} if views is None else views
    view = views.get((world, rates)) or views.setdefault((world, rates), RosView(world, rates))
    bag = Path(out_dir) / path.stem
    if bag.exists():
        shutil.rmtree(bag)
    bag.parent.mkdir(parents=True, exist_ok=True)
    undecodable = written = 0
    first_ns = None
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {t.name: writer.add_connection(t.name, t.type, typestore=typestore(),
                                                     offered_qos_profiles=qos_profiles(t)) for t in TOPICS}
        for m in episode.messages:
            mtype = BY_TOPIC.get(m.topic.lstrip("/"))
            if mtype is None:
                continue
            try:
                msg = mtype.decode(m.payload)
            except (MessageError, ValueError, UnicodeDecodeError):
                undecodable += 1
                continue
            for ros_topic, ros_msg in view.take(mtype.topic, msg):
                stamp_ns = int(msg["stamp_ns"])
                if first_ns is None:
                    first_ns = stamp_ns
                    writer.write(connections["/robot_description"], stamp_ns,
                                 to_cdr(view.description(), "std_msgs/msg/String"))
                    written += 1
                writer.write(connections[ros_topic], stamp_ns, to_cdr(ros_msg, BY_NAME[ros_topic].type))
                written += 1
    _add_type_hashes(bag / f"{bag.name}.mcap")
    note = f", {undecodable} undecodable message(s) skipped" if undecodable else ""
    return Bagged(path, bag, written, f"{written} ROS 2 messages in {bag}{note}")


def _add_type_hashes(mcap_path: Path) -> None:
    """The bag's MCAP file again, each channel's metadata with its ``topic_type_hash``."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    from services.runtime.files import write_via

    def write(tmp: Path) -> None:
        with open(mcap_path, "rb") as src, open(tmp, "wb") as dst:
            reader = make_reader(src)
            summary = reader.get_summary()
            out = Writer(dst, compression=CompressionType.ZSTD)
            header = reader.get_header()
            out.start(profile=header.profile, library=f"{header.library}; topic_type_hash by etar-bench export")
            schema_ids = {s.id: out.register_schema(s.name, s.encoding, s.data) for s in summary.schemas.values()}
            channel_ids = {}
            for c in summary.channels.values():
                metadata = dict(c.metadata, topic_type_hash=type_hash(summary.schemas[c.schema_id].name))
                channel_ids[c.id] = out.register_channel(c.topic, c.message_encoding, schema_ids[c.schema_id],
                                                         metadata)
            for _, channel, message in reader.iter_messages(log_time_order=False):
                out.add_message(channel_ids[channel.id], message.log_time, message.data, message.publish_time,
                                message.sequence)
            out.finish()
    write_via(mcap_path, write)


def export_rosbag2(run_dir, out_dir=None, rates: Ros2Rates = Ros2Rates(), progress=None) -> list[Bagged]:
    """``bag_of_recording`` for every recording of the run in ``run_dir``, into ``out_dir``
    (default ``RUN_DIR/rosbag2``)."""
    run_dir = Path(run_dir)
    folder = run_dir / "recordings"
    if not folder.is_dir():
        raise RecordingError(f"{run_dir}: no recordings/ folder: not a run's output folder")
    paths = sorted(folder.glob("*.mcap"))
    if not paths:
        raise RecordingError(f"{folder}: no .mcap recordings")
    out_dir = run_dir / BAGS_DIR if out_dir is None else Path(out_dir)
    views: dict = {}
    out = []
    for path in paths:
        result = bag_of_recording(path, out_dir, rates, views)
        out.append(result)
        if progress is not None:
            progress(result.describe())
    return out

