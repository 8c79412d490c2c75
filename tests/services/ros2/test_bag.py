"""``etar-bench export RUN --rosbag2``: a ROS 2 bag of each recording, judged by software
nobody here wrote: rosbags' own reader opens every bag and deserialises every message, the
MCAP project's ROS 2 decoder (mcap-ros2-support) reads every file; the values are the
recording's, the file is rosbag2's (the ros2 profile, ros2msg schemas, CDR, each channel's
offered QoS and type hash); bad input gets one line and no bag."""

import shutil
from collections import Counter

import numpy as np
import pytest
import yaml

from services.cli import bench as bench_cli
from services.recordings.reader import read_episode
from services.ros2.types import BY_NAME, TOPICS, type_hash, typestore
from services.runtime.messages import ESTIMATOR_PHASE, FT_WRENCH, ROBOT_STATE


@pytest.fixture(scope="module")
def bags(foxglove_run_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("bags") / "rosbag2"
    assert bench_cli.main(["export", str(foxglove_run_dir), "--rosbag2", "--out", str(out)]) == 0
    return foxglove_run_dir, out


def recorded(path, mtype) -> list[dict]:
    return [mtype.decode(m.payload) for m in read_episode(path).messages if m.topic == mtype.channel]


def test_rosbags_reads_every_message_of_every_bag_with_the_recordings_values(bags):
    from rosbags.rosbag2 import Reader

    run_dir, out = bags
    recordings = sorted((run_dir / "recordings").glob("*.mcap"))
    assert sorted(p.name for p in out.iterdir()) == [p.stem for p in recordings]
    for path in recordings:
        got: dict[str, list] = {}
        with Reader(out / path.stem) as reader:
            assert {c.topic: c.digest for c in reader.connections} == {t.name: t.hash for t in TOPICS}
            for connection, timestamp, raw in reader.messages():
                msg = typestore().deserialize_cdr(raw, connection.msgtype)
                got.setdefault(connection.topic, []).append((timestamp, msg))
        assert len(got["/robot_description"]) == 1 and "<robot" in got["/robot_description"][0][1].data
        wrenches = recorded(path, FT_WRENCH)
        assert len(got["/ft_sensor/wrench"]) == len(wrenches) > 1000  # 1 kHz: every sample
        for (t, ws), w in zip(got["/ft_sensor/wrench"], wrenches):
            f, tau = ws.wrench.force, ws.wrench.torque
            assert t == w["stamp_ns"] and [f.x, f.y, f.z, tau.x, tau.y, tau.z] == w["wrench"]
        states = [s for s in recorded(path, ROBOT_STATE) if s["seq"] % 10 == 0]
        assert len(got["/joint_states"]) == len(states) == len(got["/tf"]) == len(got["/tcp_pose"])
        for (t, js), s in zip(got["/joint_states"], states):
            assert t == s["stamp_ns"] and list(js.position) == s["msr_jnt_pos"]
        assert len(got["/clock"]) == len(recorded(path, ROBOT_STATE))
        phases = recorded(path, ESTIMATOR_PHASE)
        assert len(got.get("/etar/phase", [])) == len(phases)
        for (_, pe), p in zip(got.get("/etar/phase", []), phases):
            assert pe.phase == p["phase"] and list(pe.posterior) == p["posterior"]
    # the reproduction had an estimator; a demonstration has none
    assert recorded(run_dir / "recordings" / "reproduction_00.mcap", ESTIMATOR_PHASE)


def test_the_mcap_projects_ros_2_decoder_reads_every_file_as_rosbag2_writes_it(bags):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    _, out = bags
    for bag in sorted(out.iterdir()):
        with open(bag / f"{bag.name}.mcap", "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            assert reader.get_header().profile == "ros2"
            summary = reader.get_summary()
            for channel in summary.channels.values():
                schema = summary.schemas[channel.schema_id]
                assert (channel.message_encoding, schema.encoding) == ("cdr", "ros2msg")
                assert channel.metadata["topic_type_hash"] == type_hash(schema.name) == BY_NAME[channel.topic].hash
                qos = yaml.safe_load(channel.metadata["offered_qos_profiles"])
                durability = "transient_local" if channel.topic == "/robot_description" else "volatile"
                assert [(q["reliability"], q["durability"]) for q in qos] == [("reliable", durability)]
            counts = Counter(ch.topic for _, ch, _, decoded in reader.iter_decoded_messages())
        assert sum(counts.values()) == sum(summary.statistics.channel_message_counts.values())
        meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert meta["storage_identifier"] == "mcap" and meta["message_count"] == sum(counts.values())


def test_bad_input_gets_one_line_and_makes_no_bag(bags, tmp_path, capsys):
    run_dir, _ = bags
    assert bench_cli.main(["export", str(tmp_path), "--rosbag2"]) == 2
    assert "no recordings/ folder" in capsys.readouterr().err
    assert bench_cli.main(["export", str(run_dir)]) == 2
    assert "--rosbag2" in capsys.readouterr().err
    assert bench_cli.main(["export", str(run_dir), "--foxglove", "--out", str(tmp_path / "x")]) == 2
    assert bench_cli.main(["export", str(run_dir), "--rosbag2", "--ros2-wrench-rate-hz", "300"]) == 2
    assert "--ros2-wrench-rate-hz must divide" in capsys.readouterr().err
    # a recording cut short: said, no bag of it, the others made, exit 1
    cut = tmp_path / "cut"
    shutil.copytree(run_dir / "recordings", cut / "recordings")
    path = cut / "recordings" / "demonstration_00.mcap"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    assert bench_cli.main(["export", str(cut), "--rosbag2"]) == 1
    said = capsys.readouterr()
    assert "demonstration_00.mcap: truncated" in said.out and "no bag" in said.out
    assert not (cut / "rosbag2" / "demonstration_00").exists() and (cut / "rosbag2" / "reproduction_00").is_dir()
    assert "1 ROS 2 bag(s) of 2 recording(s)" in said.err
    assert not (tmp_path / "x").exists()
    np.testing.assert_equal(sorted(p.name for p in (run_dir / "recordings").glob("*.mcap")),
                            ["demonstration_00.mcap", "reproduction_00.mcap"])
