"""Foxglove's visual topics in the recordings: valid against Foxglove's own published JSON
Schemas (@foxglove/schemas from npm, installed by `make test`), showing the arm where the
robot measured it, and added to older recordings by `etar-bench export --foxglove`."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from services.cli import bench as bench_cli
from services.foxglove.export import add_visual_topics, export_foxglove
from services.recordings.format import RecordingError
from services.recordings.reader import read_episode
from services.recordings.recovery import write_copy
from services.foxglove.scene import ARM_ALPHA, ARROW_M_PER_N, ELLIPSOID_M_PER_N_M, FRAMES, VisualScene, world_geometry
from services.runtime.visual_topics import SCHEMA_DIR, SCHEMA_NAMES, schema_bytes
from services.foxglove.tap import VisualTap, encode

ROOT = Path(__file__).resolve().parents[3]
NPM_SCHEMAS = ROOT / ".cache" / "foxglove-schemas" / "jsonschema"  # `make foxglove-schemas`


@pytest.fixture
def run_dir(foxglove_run_dir):
    return foxglove_run_dir


def visual_messages(path):
    """{topic: [(log_time_ns, message)]} of the visual topics of one recording."""
    out = {}
    for m in read_episode(path).messages:
        if m.topic in SCHEMA_NAMES:
            out.setdefault(m.topic, []).append((m.log_time_ns, json.loads(m.payload)))
    return out


@pytest.mark.slow
def test_every_visual_message_is_valid_against_foxglove_own_json_schemas(run_dir):
    if not (NPM_SCHEMAS / "VERSION").exists():
        pytest.skip(f"{NPM_SCHEMAS} is missing: `make foxglove-schemas` (part of `make test`) installs "
                    "@foxglove/schemas from npm")
    import jsonschema

    validators = {}
    for topic, name in SCHEMA_NAMES.items():
        if name.startswith("foxglove."):
            npm = json.loads((NPM_SCHEMAS / f"{name.split('.', 1)[1]}.json").read_text())
            # what the recordings carry is Foxglove's schema, unchanged
            assert json.loads(schema_bytes(topic)) == npm, name
        else:
            npm = json.loads(schema_bytes(topic))
        cls = jsonschema.validators.validator_for(npm)
        cls.check_schema(npm)
        validators[topic] = cls(npm)
    counts = {}
    for path in sorted((run_dir / "recordings").glob("*.mcap")):
        episode = read_episode(path)
        for topic, ch in episode.channels.items():
            if topic in SCHEMA_NAMES:
                assert (ch.schema_name, ch.schema_encoding, ch.message_encoding) == \
                    (SCHEMA_NAMES[topic], "jsonschema", "json")
                assert ch.schema_data == schema_bytes(topic)
        for topic, messages in visual_messages(path).items():
            for _, msg in messages:
                errors = [f"{e.json_path}: {e.message}" for e in validators[topic].iter_errors(msg)]
                assert not errors, (path.name, topic, errors[:3])
            counts[topic] = counts.get(topic, 0) + len(messages)
    # every frame's topics at the visual rate; the geometry once a second; the log on events
    assert set(counts) == set(SCHEMA_NAMES), counts
    assert all(n > 50 for t, n in counts.items() if t not in ("/viz/log", "/viz/geometry")), counts
    # and the validator does reject what Foxglove would not read
    bad = visual_messages(run_dir / "recordings" / "reproduction_00.mcap")["/viz/scene"][0][1]
    bad["entities"][0]["frame_id"] = 7
    assert any(e.json_path.endswith("frame_id") for e in validators["/viz/scene"].iter_errors(bad))


@pytest.mark.slow
def test_the_visual_topics_show_the_arm_where_the_robot_measured_it(run_dir):
    path = run_dir / "recordings" / "reproduction_00.mcap"
    states, wrenches = {}, []
    for m in read_episode(path).messages:
        if m.topic == "/robot/state":
            d = json.loads(m.payload)
            states[d["stamp_ns"]] = d
        elif m.topic == "/ft/wrench":
            wrenches.append((m.log_time_ns, json.loads(m.payload)["wrench"]))
    visual = visual_messages(path)
    # 50 Hz: one frame in every 20 FRI cycles
    seqs = [msg["seq"] for _, msg in visual["/viz/status"]]
    assert seqs and all(s % 20 == 0 for s in seqs) and np.all(np.diff(seqs) == 20)
    for _, tf in visual["/viz/tf"]:
        by_child = {t["child_frame_id"]: t for t in tf["transforms"]}
        assert tuple(by_child) == FRAMES and all(t["parent_frame_id"] == "base" for t in tf["transforms"])
        tcp = by_child["tcp"]
        stamp = tcp["timestamp"]["sec"] * 1_000_000_000 + tcp["timestamp"]["nsec"]
        pose = np.asarray(states[stamp]["msr_cart_pos"]).reshape(3, 4)
        # Pinocchio's tcp from the measured joints is the pose the robot reported
        t = tcp["translation"]
        np.testing.assert_allclose([t["x"], t["y"], t["z"]], pose[:, 3], atol=1e-9)
        q = tcp["rotation"]
        w, x, y, z = q["w"], q["x"], q["y"], q["z"]
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        np.testing.assert_allclose(R, pose[:, :3], atol=1e-9)
    scenes = [msg for _, msg in visual["/viz/scene"]]
    static = [msg for _, msg in visual["/viz/geometry"]]
    # the first frame, then once a second, each with the whole geometry: a seek finds it
    assert 1 <= len(static) <= len(scenes) // 40 + 2
    assert all({e["id"] for e in g["entities"]} == {e["id"] for e in static[0]["entities"]} for g in static)
    assert not any(e["id"].startswith("geometry/") for s in scenes for e in s["entities"])
    world = next(e for e in static[0]["entities"] if e["id"] == "geometry/base")
    assert world["frame_id"] == "base" and len(world["cubes"]) == 3  # two plates and the stand
    arm = {e["frame_id"] for e in static[0]["entities"] if e["id"].startswith("geometry/")} - {"base"}
    # every body of the MuJoCo arm with a geom (links 2, 4 and 6 have zero length in the DH model)
    assert arm == {frame for frame, *_ in world_geometry("valley")} - {"base"}
    assert {"link1", "link3", "link5", "link7", "ati_sensor", "tool"} <= arm
    # the arm see-through, the world not
    alphas = {e["frame_id"]: {p["color"]["a"] for kind in ("cubes", "cylinders", "spheres") for p in e[kind]}
              for e in static[0]["entities"]}
    assert alphas["base"] == {1.0} and all(a <= {ARM_ALPHA} for f, a in alphas.items() if f != "base")
    # the overlays: the arrow is the newest measured force, the ellipsoid the commanded stiffness
    statuses = [msg for _, msg in visual["/viz/status"]]
    moved, stiffnesses = 0, []
    for scene, status in zip(scenes, statuses):
        wrench = next(e for e in scene["entities"] if e["id"] == "overlay/wrench")
        tcp = next(e for e in scene["entities"] if e["id"] == "overlay/tcp")
        force = np.linalg.norm(status["force"])
        assert status["force_norm"] == pytest.approx(force)
        if wrench["arrows"]:
            a = wrench["arrows"][0]
            assert a["shaft_length"] + a["head_length"] == pytest.approx(min(force * ARROW_M_PER_N, 0.4))
            # from the contact, in base: not inside the sensor, where the viewer cannot show it
            p = a["pose"]["position"]
            assert wrench["frame_id"] == "base" and [p["x"], p["y"], p["z"]] == pytest.approx(status["tcp"])
            moved += 1
        stiffness = next(e for e in scene["entities"] if e["id"] == "overlay/stiffness")
        if status["stiffness"]:
            (ellipsoid,) = stiffness["spheres"]
            size = sorted(ellipsoid["size"].values(), reverse=True)
            assert size == pytest.approx([max(k * ELLIPSOID_M_PER_N_M, 0.004) for k in status["stiffness"]])
            p = ellipsoid["pose"]["position"]
            assert [p["x"], p["y"], p["z"]] == pytest.approx(status["tcp"])
            stiffnesses.append(status["stiffness"])
        assert tcp["texts"][0]["text"].startswith(f"phase {status['phase']}" if status["phase"] >= 0 else "phase -")
    assert moved > len(statuses) // 2  # in contact most of the reproduction
    # the learned phases' stiffness: stiff (2000 N/m) along the motion, soft (100 N/m) on a compliant axis
    assert len(stiffnesses) > len(statuses) // 2
    assert {round(k) for ks in stiffnesses for k in ks} <= {100, 2000}
    assert any(min(ks) < 200 for ks in stiffnesses) and any(max(ks) > 1500 for ks in stiffnesses)
    assert {s["phase"] for s in statuses} >= {0, 1} and {s["true_phase"] for s in statuses} >= {0, 1}
    logs = [msg["message"] for _, msg in visual["/viz/log"]]
    assert any(line.startswith("episode_begin reproduction") for line in logs)
    assert any(line.startswith("reproduction 0 ended: goal_reached") for line in logs)


@pytest.mark.slow
def test_every_episode_has_its_picture_from_its_first_visual_frame(run_dir):
    """The first frame of every episode, the first of each stage included, is drawn: the
    transforms and the geometry at the first visual cycle after the first measurement."""
    for path in sorted((run_dir / "recordings").glob("*.mcap")):
        messages = read_episode(path).messages
        first_state = min(json.loads(m.payload)["stamp_ns"] for m in messages if m.topic == "/robot/state")
        visual = visual_messages(path)
        for topic in ("/viz/tf", "/viz/geometry", "/viz/scene"):
            stamps = [support_stamp(msg, topic) for _, msg in visual[topic]]
            assert min(stamps) - first_state < 20_000_000, (path.name, topic)  # within a visual period (20 ms)


def support_stamp(msg: dict, topic: str) -> int:
    t = msg["transforms"][0]["timestamp"] if topic == "/viz/tf" else msg["entities"][0]["timestamp"]
    return t["sec"] * 1_000_000_000 + t["nsec"]


def test_visual_messages_are_written_for_any_json_parser_and_refuse_nan(run_dir):
    """encode (orjson) writes what the standard library reads back as its own encoding's
    values, exponents and all; a NaN, which a viewer's parser refuses, is an error."""
    seen = 0
    for path in sorted((run_dir / "recordings").glob("*.mcap"))[:1]:
        for topic, messages in visual_messages(path).items():
            for _, message in messages:
                assert json.loads(encode(message)) == json.loads(json.dumps(message)), topic
                seen += 1
    assert seen > 100
    values = [1e-7, -0.0, 1e22, 0.1, 5e-324]
    back = json.loads(encode({"x": values}))["x"]
    assert back == values and [math.copysign(1.0, v) for v in back] == [math.copysign(1.0, v) for v in values]
    with pytest.raises(ValueError):
        encode({"pose": {"x": float("nan")}})


def test_a_visual_tap_skips_garbage_and_counts_it():
    tap = VisualTap(VisualScene("valley"))
    assert tap.take("ft/wrench", b'{"seq":1,"wrench":"not a wrench"}') == []
    assert tap.take("robot/state", b'{"seq":20, garbage') == []  # a frame's state that does not decode
    assert tap.undecodable == 1
    assert tap.take("robot/state", b'{"seq":21, garbage') == []  # not a frame: not even decoded
    assert tap.take("runner/event", b"\xff\xfe") == [] and tap.undecodable == 2
    with pytest.raises(ValueError, match="unknown world 'moon'"):
        VisualScene("moon")
    with pytest.raises(ValueError, match="visual rate"):
        VisualScene("valley", rate_hz=0)
    assert sorted(p.name for p in SCHEMA_DIR.glob("*.json")) == ["FrameTransforms.json", "Log.json",
                                                                 "SceneUpdate.json"]


@pytest.mark.slow
@pytest.mark.parametrize("writer_process", [False, True], ids=["in the recorder", "in the writer's helper"])
def test_the_recorder_draws_the_visual_topics_a_run_recorded(run_dir, tmp_path, writer_process):
    """The recorder over Zenoh draws the scene itself; in one process the MCAP writer's
    helper process does (one CPU carries every node there).  Fed a recorded episode's own
    messages as they came, either gives that episode's visual messages, byte for byte and
    at the same log times; a frame's state that does not decode is counted in the
    recorder's status, once its episode is finished."""
    from services.nodes.recorder import RecorderConfig, RecorderNode

    source = sorted((run_dir / "recordings").glob("reproduction_*.mcap"))[0]
    episode = read_episode(source)
    recorder = RecorderNode(RecorderConfig(out_dir=str(tmp_path), writer_process=writer_process), None, None,
                            run_id="foxglove")
    try:
        recorder.begin({"path": "again.mcap", "kind": "reproduction", "index": 0,
                        "scenario": episode.scenario_text})
        own = [m for m in episode.messages if m.topic not in SCHEMA_NAMES]
        for m in own:
            recorder.on_sample(m.topic.lstrip("/"), m.log_time_ns, m.payload)
        recorder.on_sample("robot/state", own[-1].log_time_ns + 1, b'{"seq":400000, garbage')
        assert recorder.end({})["messages"] == len(episode.messages) + 1
        assert recorder.status()["visual_undecodable"] == 1 and recorder.status()["visual_errors"] == 0
    finally:
        recorder.close()
    drawn = [(m.topic, m.log_time_ns, m.payload) for m in read_episode(tmp_path / "again.mcap").messages
             if m.topic in SCHEMA_NAMES]
    recorded = [(m.topic, m.log_time_ns, m.payload) for m in episode.messages if m.topic in SCHEMA_NAMES]
    assert len(recorded) > 100 and drawn == recorded


def strip_visual(src: Path, dst: Path) -> dict:
    """Copies of ``src``'s recordings without the visual topics (a recording made before
    they existed); the visual messages each had."""
    (dst / "recordings").mkdir(parents=True)
    had = {}
    for path in sorted((src / "recordings").glob("*.mcap")):
        episode = read_episode(path)
        had[path.name] = [m for m in episode.messages if m.topic in SCHEMA_NAMES]
        episode.messages[:] = [m for m in episode.messages if m.topic not in SCHEMA_NAMES]
        for topic in SCHEMA_NAMES:
            episode.channels.pop(topic, None)
        write_copy(episode, dst / "recordings" / path.name, library="test", metadata=episode.metadata)
    return had


@pytest.mark.slow
def test_export_adds_the_visual_topics_the_recorder_would_have_written(run_dir, tmp_path, capsys):
    old = tmp_path / "old"
    had = strip_visual(run_dir, old)
    before = {p.name: read_episode(p).messages for p in (old / "recordings").glob("*.mcap")}
    assert bench_cli.main(["export", str(old), "--foxglove"]) == 0
    assert "visual topics added to 2 of 2 recording(s)" in capsys.readouterr().err
    for path in sorted((old / "recordings").glob("*.mcap")):
        episode = read_episode(path)
        assert episode.complete
        # the run's own messages byte for byte, the visual ones as the recorder wrote them
        assert [m for m in episode.messages if m.topic not in SCHEMA_NAMES] == before[path.name]
        assert [m for m in episode.messages if m.topic in SCHEMA_NAMES] == had[path.name]
        assert episode.metadata["visual_topics_added_by"] == "etar-bench export --foxglove"
    again = export_foxglove(old)
    assert all(r.added == 0 and "already" in r.why for r in again)


@pytest.mark.slow
def test_export_refuses_what_it_cannot_read_and_leaves_it_as_it_was(run_dir, tmp_path, capsys):
    assert bench_cli.main(["export", str(tmp_path), "--foxglove"]) == 2  # no run folder: a usage error
    assert "no recordings/ folder" in capsys.readouterr().err
    assert bench_cli.main(["export", str(run_dir)]) == 2
    assert "--foxglove" in capsys.readouterr().err
    assert bench_cli.main(["export", str(run_dir), "--foxglove", "--visual-rate-hz", "0"]) == 2
    old = tmp_path / "old"
    strip_visual(run_dir, old)
    path = sorted((old / "recordings").glob("*.mcap"))[0]
    # truncated: left alone, said why
    data = path.read_bytes()
    cut = old / "recordings" / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    result = add_visual_topics(cut)
    assert result.added == 0 and "etar-bench recover" in result.why and cut.read_bytes() == data[: len(data) * 2 // 3]
    # no scenario to say which world: an error naming the file and the attachment, nothing changed
    episode = read_episode(path)
    episode.attachments.clear()
    bare = old / "recordings" / "bare.mcap"
    write_copy(episode, bare, library="test", metadata=episode.metadata)
    before = bare.read_bytes()
    with pytest.raises(RecordingError, match=r"bare.mcap: no 'scenario.yaml' attachment"):
        add_visual_topics(bare)
    assert bare.read_bytes() == before
    shutil.rmtree(old)


@pytest.mark.zenoh
def test_a_services_log_line_crosses_the_wire_and_becomes_a_foxglove_log_line(capsys):
    import threading

    from services.runtime import topics
    from services.runtime.messages import SERVICE_LOG
    from tests.services.conftest import service_with_peer

    got, arrived = [], threading.Event()
    with service_with_peer("phase_estimator", "svclog") as (svc, run_id, peer):
        sub = peer.declare_subscriber(topics.key(run_id, "service/log"),
                                      lambda s: (got.append(bytes(s.payload.to_bytes())), arrived.set()))
        # the service's publisher says when the subscription has reached it
        pub, matched = svc.publisher("service/log", realtime=False), threading.Event()
        listener = pub.declare_matching_listener(lambda status: status.matching and matched.set())
        assert pub.matching_status.matching or matched.wait(5), "the subscription never reached the service"
        listener.undeclare()
        svc.log("model reloaded", level=3)
        assert arrived.wait(5)
        sub.undeclare()
    assert "[phase_estimator] model reloaded" in capsys.readouterr().err  # stderr keeps it
    msg = SERVICE_LOG.decode(got[0])
    assert (msg["role"], msg["level"], msg["text"], msg["seq"]) == ("phase_estimator", 3, "model reloaded", 0)
    tap = VisualTap(VisualScene("valley"))
    (line,) = tap.take("service/log", got[0])
    assert line[0] == "/viz/log" and line[1]["name"] == "phase_estimator" and line[1]["level"] == 3
    assert line[1]["message"] == "model reloaded"


def test_the_layout_refers_only_to_panels_it_configures_and_fields_the_visual_topics_have():
    layout = json.loads((ROOT / "docs" / "foxglove" / "etar.layout.json").read_text())
    assert set(layout) >= {"configById", "layout", "globalVariables", "userNodes"}

    def leaves(node):
        if isinstance(node, str):
            return [node]
        assert set(node) >= {"first", "second", "direction"} and node["direction"] in ("row", "column")
        return leaves(node["first"]) + leaves(node["second"])

    panels = leaves(layout["layout"])
    assert sorted(panels) == sorted(layout["configById"])  # every panel shown is configured, and no other
    assert {p.split("!")[0] for p in panels} == {"3D", "Plot", "StateTransitions", "RosOut"}
    status = json.loads(schema_bytes("/viz/status"))["properties"]
    paths = [p["value"] for cfg in layout["configById"].values() for p in cfg.get("paths", [])]
    assert paths
    for path in paths:
        topic, _, field = path.partition(".")
        assert topic == "/viz/status", path
        assert field.split("[")[0] in status, path
    assert set(layout["configById"]["3D!arm"]["topics"]) == {"/viz/geometry", "/viz/scene", "/viz/tf"}
    # frame labels and axes in proportion to a 1 m arm, not the viewer's 0.2 m labels
    transforms = layout["configById"]["3D!arm"]["scene"]["transforms"]
    assert transforms["labelSize"] <= 0.05 and transforms["axisScale"] <= 0.5
    assert layout["configById"]["RosOut!log"]["topicToRender"] == "/viz/log"
