"""Episode recordings: MCAP round trip, schemas, bad payloads, truncated files,
and a real simulated demonstration through load_demonstration and ``etar learn``."""

import json
import os
import re
import signal
import subprocess
import sys

import numpy as np
import pytest
from mcap.reader import make_reader
from scipy.spatial.transform import Rotation

from services.recordings.writer import EpisodeWriter
from services.recordings.format import RecordingError
from services.recordings.demonstrations import load_demonstration
from services.recordings.reader import read_episode
from services.runtime.messages import (BY_TOPIC, ESTIMATOR_PHASE, FT_WRENCH, ROBOT_COMMAND, ROBOT_CONTACT,
                                       ROBOT_STATE, RUNNER_EVENT, TEACHER_WRENCH)
from services.run.demonstration import demonstration_scenario, record_demonstration
from tests.support import recorded_samples

RUN = "r42"
SCENARIO = "name: valley\nstages:\n  - demonstrate: {episodes: 1}\n"


def key(topic: str) -> str:
    return f"etar/{RUN}/{topic}"


def header(seq, sent_ns=None):
    return dict(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=1_000_000_000 + seq * 1000 if sent_ns is None else sent_ns)


def state_payload(seq, rng):
    pose = np.concatenate([np.eye(3), rng.normal(size=(3, 1))], axis=1).reshape(-1)
    return ROBOT_STATE.encode(**header(seq), reflected_seq=seq - 1, fri_state=2, fri_quality=3, control_mode=2,
                              msr_jnt_pos=rng.normal(size=7), msr_cart_pos=pose, est_ext_tcp_ft=rng.normal(size=6),
                              answer_rate=1.0, latency_s=2e-4, jitter_s=1e-5, miss_rate=0.0, safety=0,
                              gravity_compensation=True, episode=0)


def ft_payload(seq, rng):
    w = rng.normal(size=6)
    return FT_WRENCH.encode(**header(seq), rdt_sequence=seq, ft_sequence=seq, status=0,
                            counts=[int(x) for x in w * 1e6], counts_per_force=1e6, counts_per_torque=1e6, wrench=w)


def mixed_messages(n_cycles, rng):
    """(key expression, payload, log time) of several topics, robot-cycle style."""
    out = []
    for seq in range(1, n_cycles + 1):
        t = 5_000_000_000 + seq * 1_000_000
        out.append((key("robot/state"), state_payload(seq, rng), t))
        out.append((key("robot/contact"), ROBOT_CONTACT.encode(**header(seq), wrench=rng.normal(size=6),
                                                               contact_force=rng.normal(size=3), touching=["plate_left"],
                                                               true_phase=1, episode=0), t + 20_000))
        out.append((key("ft/wrench"), ft_payload(seq, rng), t + 40_000))
        out.append((key("teacher/wrench"), TEACHER_WRENCH.encode(**header(seq), wrench=rng.normal(size=6),
                                                                 script_phase=1, done=False, episode=0), t + 30_000))
        out.append((key("robot/command"), ROBOT_COMMAND.encode(
            **header(seq), cart_pos=rng.normal(size=12), cart_stiffness=[1000.0] * 3 + [100.0] * 3,
            cart_damping=[0.7] * 6, add_tcp_ft=[0.0] * 6, requested_mode=2, phase=0, estimate_seq=-1,
            goal_reached=False, hold="",
            episode=0), t + 50_000))
        if seq % 10 == 0:
            out.append((key("estimator/phase"), ESTIMATOR_PHASE.encode(
                **header(seq), posterior=[0.2, 0.8], phase=1, input_seq=seq, ft_seq=seq, episode=0), t + 60_000))
    out.append((key("runner/event"), RUNNER_EVENT.encode(**header(0), event="episode_end", stage="demonstrate",
                                                         episode=0, info={"note": "done"}), 4_000_000_000))
    return out


def write_episode(path, messages, **kwargs):
    kwargs.setdefault("scenario_text", SCENARIO)
    with EpisodeWriter(path, run_id=RUN, episode_kind="demonstration", episode_index=3, **kwargs) as w:
        for k, payload, t in messages:
            w.add(k, payload, t)
    return w


def expected(messages):
    rows = [(k[len(f"etar/{RUN}"):], t, p) for k, p, t in messages]
    return sorted(rows, key=lambda r: r[1])  # stable: equal times keep their order


# ---------------------------------------------------------------------------
# round trip
# ---------------------------------------------------------------------------


def test_round_trip_is_byte_identical_in_log_time_order(tmp_path, rng):
    messages = mixed_messages(200, rng)
    path = tmp_path / "ep.mcap"
    w = write_episode(path, messages, metadata={"seed": 7, "side": "left"})
    assert (w.messages_written, w.bad_payloads) == (len(messages), 0)

    ep = read_episode(path)
    assert ep.complete and ep.problem is None
    assert [tuple(m)[:3] for m in ep.messages] == expected(messages)
    assert all(type(m.payload) is bytes for m in ep.messages)
    assert ep.scenario_text == SCENARIO
    assert ep.attachments == {"scenario.yaml": SCENARIO.encode()}
    assert ep.metadata["run_id"] == RUN
    assert ep.metadata["episode_kind"] == "demonstration"
    assert ep.metadata["episode_index"] == "3"
    assert ep.metadata["seed"] == "7" and ep.metadata["side"] == "left"
    assert all(isinstance(v, str) for v in ep.metadata.values())


def test_indexed_reader_sees_the_same_file(tmp_path, rng):
    """What Foxglove-style seeking readers use: summary, chunk indexes, publish times, attachment index."""
    messages = mixed_messages(50, rng)
    path = tmp_path / "ep.mcap"
    write_episode(path, messages)
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary.statistics.message_count == len(messages)
        assert summary.chunk_indexes and all(ci.compression == "zstd" for ci in summary.chunk_indexes)
        got = [(ch.topic, m.log_time, m.publish_time, m.data) for _, ch, m in reader.iter_messages()]
        attachments = list(reader.iter_attachments())
        metadata = list(reader.iter_metadata())
    # publish time is the sender's sent_ns header
    for topic, _, publish, data in got:
        assert publish == json.loads(data)["sent_ns"]
    assert [(t, lt, d) for t, lt, _, d in got] == expected(messages)
    assert [(a.name, a.media_type, a.data) for a in attachments] == [("scenario.yaml", "application/yaml",
                                                                      SCENARIO.encode())]
    assert [m.name for m in metadata] == ["etar"]


def test_every_channel_has_a_jsonschema_schema(tmp_path, rng):
    messages = mixed_messages(10, rng) + [(key("custom/thing"), b'{"seq": 1, "x": 2}', 6_000_000_000)]
    path = tmp_path / "ep.mcap"
    write_episode(path, messages)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    topics = set()
    for ch in summary.channels.values():
        topics.add(ch.topic)
        assert ch.message_encoding == "json"
        assert ch.metadata["key_expr"] == key(ch.topic[1:])
        assert ch.schema_id != 0
        schema = summary.schemas[ch.schema_id]
        assert schema.encoding == "jsonschema"
        parsed = json.loads(schema.data)
        assert parsed["type"] == "object"
        mtype = BY_TOPIC.get(ch.topic[1:])
        if mtype is not None:
            assert schema.name == mtype.name and parsed == mtype.json_schema()
    assert topics == {"/robot/state", "/robot/contact", "/ft/wrench", "/teacher/wrench", "/robot/command",
                      "/estimator/phase", "/runner/event", "/custom/thing"}
    assert {c.topic: c.schema_encoding for c in read_episode(path).channels.values()} == dict.fromkeys(
        topics, "jsonschema")


def test_bad_payloads_are_recorded_and_counted(tmp_path, rng):
    good = state_payload(1, rng)
    bad = [b"not json at all", b'{"seq": 2}', state_payload(3, rng).replace(b'"safety":0', b'"safety":"x"'),
           b"\xff\xfe", b"[1, 2]"]
    path = tmp_path / "ep.mcap"
    with EpisodeWriter(path, run_id=RUN, episode_kind="demonstration", episode_index=0) as w:
        w.add(key("robot/state"), good, 10)
        for i, payload in enumerate(bad):
            w.add(key("robot/state"), payload, 20 + i)
        w.add(key("custom/thing"), b"neither", 30)  # no definition, and not JSON either
        w.add(key("custom/thing"), bytearray(b'{"sent_ns": 5}'), 31)
    assert w.messages_written == 8
    assert w.bad_payloads == 6
    ep = read_episode(path)
    assert [m.payload for m in ep.messages] == [good, *bad, b"neither", b'{"sent_ns": 5}']
    assert ep.scenario_text is None
    with open(path, "rb") as f:
        publish = [m.publish_time for _, _, m in make_reader(f).iter_messages()]
    assert publish == [json.loads(good)["sent_ns"], 20, 21, 22, 23, 24, 30, 5]


def test_writer_lifetime_and_misuse(tmp_path, rng):
    path = tmp_path / "ep.mcap"
    w = EpisodeWriter(path, run_id=RUN, episode_kind="reproduction", episode_index=1)
    with pytest.raises(RecordingError, match="not under 'etar/r42/'"):
        w.add("etar/other/robot/state", state_payload(1, rng), 1)
    with pytest.raises(TypeError):
        w.add(key("robot/state"), "text", 1)
    with pytest.raises(ValueError):
        w.add(key("robot/state"), state_payload(1, rng), -1)
    w.add(key("robot/state"), state_payload(1, rng), 1, publish_time_ns=1)
    w.finish()
    w.finish()  # idempotent
    with pytest.raises(RecordingError, match="after finish"):
        w.add(key("robot/state"), state_payload(2, rng), 2)
    assert len(read_episode(path).messages) == 1
    with pytest.raises(RecordingError, match="reserved"):
        EpisodeWriter(tmp_path / "x.mcap", run_id=RUN, episode_kind="demonstration", episode_index=0,
                      metadata={"run_id": "other"})
    # an exception inside the with block still leaves a finished, readable file
    with pytest.raises(KeyError):
        with EpisodeWriter(tmp_path / "y.mcap", run_id=RUN, episode_kind="demonstration", episode_index=0) as w:
            w.add(key("ft/wrench"), ft_payload(1, rng), 5)
            raise KeyError("boom")
    assert read_episode(tmp_path / "y.mcap").complete


# ---------------------------------------------------------------------------
# damaged files
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def long_episode(tmp_path_factory):
    """An episode spanning several chunks (CHUNK_SIZE)."""
    rng = np.random.default_rng(11)
    messages = [(key("robot/state"), state_payload(s, rng), 1_000_000 * s) for s in range(1, 3001)]
    path = tmp_path_factory.mktemp("long") / "long.mcap"
    write_episode(path, messages)
    return path, expected(messages)


def test_truncated_file_gives_complete_chunks_or_a_clear_error(tmp_path, long_episode):
    path, want = long_episode
    data = path.read_bytes()
    ep = read_episode(path)
    assert ep.complete and ep.chunks >= 4
    recovered = {}
    for cut in (4, 20, 200, len(data) // 3, len(data) // 2, 2 * len(data) // 3, len(data) - 300, len(data) - 8,
                len(data) - 1):
        cut_path = tmp_path / f"cut_{cut}.mcap"
        cut_path.write_bytes(data[:cut])
        try:
            ep = read_episode(cut_path)
        except RecordingError as exc:
            assert str(cut_path) in str(exc)
            recovered[cut] = None
            continue
        assert not ep.complete
        assert ep.problem and ("footer" in ep.problem or cut >= len(data) - 8 and "closing magic" in ep.problem)
        # a prefix of what was written, byte for byte
        assert [tuple(m)[:3] for m in ep.messages] == want[: len(ep.messages)]
        assert ep.metadata["run_id"] == RUN and ep.scenario_text == SCENARIO
        recovered[cut] = len(ep.messages)
    assert recovered[4] is None and recovered[20] is None  # not even the header
    assert recovered[200] in (None, 0)  # at most the metadata and the scenario
    # mid-file: the complete chunks before the cut
    assert 0 < recovered[len(data) // 2] < len(want)
    assert recovered[len(data) // 3] <= recovered[len(data) // 2] <= recovered[2 * len(data) // 3]
    # cut in the summary, or in the closing magic alone: every message is there, the file is
    # still not complete
    assert recovered[len(data) - 300] == recovered[len(data) - 8] == recovered[len(data) - 1] == len(want)
    with pytest.raises(RecordingError, match="incomplete"):
        load_demonstration(tmp_path / f"cut_{len(data) // 2}.mcap")


def test_recover_makes_a_truncated_file_a_finished_one_with_every_complete_chunk(tmp_path, long_episode, capsys):
    from services.cli.bench import main as bench
    from services.recordings.recovery import recover

    path, want = long_episode
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    kept = read_episode(cut)
    assert not kept.complete and 0 < len(kept.messages) < len(want)
    result = recover(cut)
    assert result.path == tmp_path / "cut.recovered.mcap" and result.messages == len(kept.messages)
    assert cut.read_bytes() == data[: len(data) // 2]  # the original is kept as it was
    back = read_episode(result.path)
    assert back.complete and back.problem is None
    assert [tuple(m) for m in back.messages] == [tuple(m) for m in kept.messages]
    assert [tuple(m)[:3] for m in back.messages] == want[: len(back.messages)]
    assert back.scenario_text == SCENARIO and back.metadata["run_id"] == RUN
    assert back.metadata["recovered_from"] == "cut.mcap" and "footer" in back.metadata["recovered"]
    assert result.last_robot_seq == json.loads(kept.messages[-1].payload)["seq"]
    # a seeking reader (what Foxglove and `mcap info` use) opens it: it has a summary
    with open(result.path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary().statistics.message_count == len(kept.messages)
        assert sum(1 for _ in reader.iter_messages()) == len(kept.messages)
    # the command line: one line per file; errors name the file, exit non-zero
    assert bench(["recover", str(cut), "--out", str(tmp_path / "again.mcap")]) == 0
    assert f"recovered {len(kept.messages)} messages" in capsys.readouterr().out
    assert bench(["recover", str(cut)]) == 1
    assert "exists (pass --force" in capsys.readouterr().err
    assert bench(["recover", str(cut), "--force"]) == 0
    # a finished one (among the files of a folder, say): nothing to do, and no failure
    assert bench(["recover", str(path)]) == 0
    assert f"{path}: a finished recording" in capsys.readouterr().out
    assert bench(["recover", str(path), str(cut), "--force"]) == 0
    # a copy a byte short (only the closing magic cut): every message recovered
    short = tmp_path / "short.mcap"
    short.write_bytes(data[:-1])
    assert bench(["recover", str(short)]) == 0
    assert f"recovered {len(want)} messages" in capsys.readouterr().out
    assert read_episode(tmp_path / "short.recovered.mcap").complete
    header_only = tmp_path / "header.mcap"
    header_only.write_bytes(data[:20])
    assert bench(["recover", str(header_only)]) == 1
    assert str(header_only) in capsys.readouterr().err
    assert bench(["recover", str(cut), str(path), "--out", str(tmp_path / "x.mcap")]) == 2
    capsys.readouterr()
    # --out refused before anything is written, in one line, exit 2 (a folder, a missing
    # folder, an existing file without --force); nothing is left behind
    folder = tmp_path / "outdir"
    folder.mkdir()
    for out, force, said in ((folder, True, "a folder; --out names the output file"),
                             (tmp_path / "missing" / "x.mcap", False, f"its folder {tmp_path / 'missing'} does not"),
                             (tmp_path / "again.mcap", False, "exists (pass --force to replace it)")):
        assert bench(["recover", str(cut), "--out", str(out)] + (["--force"] if force else [])) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"--out {out}: {said}" in err[0], err
    assert list(folder.iterdir()) == [] and not list(tmp_path.glob("*.part"))


def test_recover_keeps_the_chunks_before_damage_inside_a_finished_file(tmp_path, long_episode, capsys):
    from services.cli.bench import main as bench
    from services.recordings.recovery import recover

    path, want = long_episode
    data = bytearray(path.read_bytes())
    damaged = tmp_path / "damaged.mcap"
    data[len(data) // 2:len(data) // 2 + 64] = bytes(64)  # zeros in the middle of the data section
    damaged.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="corrupt MCAP file"):
        read_episode(damaged)  # what every reader but recover says of it
    result = recover(damaged)
    back = read_episode(result.path)
    assert back.complete and 0 < len(back.messages) == result.messages < len(want)
    assert [tuple(m)[:3] for m in back.messages] == want[:len(back.messages)]  # a prefix, byte for byte
    assert back.metadata["recovered"].startswith("corrupt MCAP file") and \
        f"{result.chunks} complete chunk(s) recovered; the messages of the chunk found damaged and after it are lost" \
        in back.metadata["recovered"]
    assert result.describe().endswith(back.metadata["recovered"])  # what was lost, in the reader's words
    # damage in the first chunk: nothing before it to keep, a failure naming the file
    first = tmp_path / "first.mcap"
    data = bytearray(path.read_bytes())
    with open(path, "rb") as f:
        start = make_reader(f).get_summary().chunk_indexes[0].chunk_start_offset
    data[start + 100:start + 164] = bytes(64)
    first.write_bytes(bytes(data))
    assert bench(["recover", str(first)]) == 1
    assert str(first) in capsys.readouterr().err


def test_killed_writer_leaves_its_complete_chunks(tmp_path):
    path = tmp_path / "killed.mcap"
    script = f"""
import os, signal
from services.recordings.writer import EpisodeWriter
w = EpisodeWriter({str(path)!r}, run_id={RUN!r}, episode_kind="demonstration", episode_index=0,
                  scenario_text="x: 1\\n")
for s in range(1, 2501):
    w.add({key("custom/pad")!r}, b'{{"seq":%d,"pad":"%s"}}' % (s, os.urandom(200).hex().encode()), s)
os.kill(os.getpid(), signal.SIGKILL)
"""
    proc = subprocess.run([sys.executable, "-c", script], cwd=os.getcwd(), capture_output=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()
    ep = read_episode(path)
    assert not ep.complete
    assert ep.chunks >= 2 and 0 < len(ep.messages) < 2500
    assert [m.log_time_ns for m in ep.messages] == list(range(1, len(ep.messages) + 1))
    assert ep.scenario_text == "x: 1\n"


def test_corrupt_or_foreign_files_raise_naming_the_file(tmp_path, long_episode):
    path, _ = long_episode
    data = bytearray(path.read_bytes())
    data[len(data) // 2: len(data) // 2 + 64] = bytes(64)  # zeros inside a chunk of a finished file
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="corrupt") as info:
        read_episode(bad)
    assert str(bad) in str(info.value)
    foreign = tmp_path / "notes.mcap"
    foreign.write_bytes(b"this is not an MCAP file, just text\n" * 4)
    with pytest.raises(RecordingError, match="not a readable MCAP file|not an MCAP file"):
        read_episode(foreign)
    with pytest.raises(RecordingError, match="no such file"):
        read_episode(tmp_path / "missing.mcap")
    with pytest.raises(RecordingError, match=r"not a regular file \(a folder\)"):
        read_episode(tmp_path)
    # what would block the open (a FIFO with no writer) or never end (/dev/zero) is refused unread
    fifo = tmp_path / "live.mcap"
    os.mkfifo(fifo)
    for special in (fifo, "/dev/zero"):
        with pytest.raises(RecordingError, match="not a regular file"):
            read_episode(special)


# ---------------------------------------------------------------------------
# a real simulated demonstration
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def simulated_demo(tmp_path_factory):
    """A short valley demonstration (all three phases) run by the nodes and recorded as
    they publish it, every cycle, and the reference at 100 Hz read from the recording's
    messages with plain json (``tests.support.recorded_samples``, which shares no code
    with load_demonstration)."""
    # close to the plate, so all three phases fit in a few seconds; the right side: y = +0.06
    scenario = demonstration_scenario("valley", side="right", start=(0.68, -0.06, 0.34), goal_x=0.60,
                                      max_seconds=8.0, seed=0)
    report, path = record_demonstration(scenario, tmp_path_factory.mktemp("demo"), progress=lambda line: None)
    assert report["error"] is None, report["error"]
    (demo,) = report["demonstrations"]
    assert demo["reason"] == "teacher_done" and demo["start"] == [0.68, 0.06, 0.34]
    assert demo["undecodable_messages"] == 0
    samples = recorded_samples(path)
    R = samples["R"]
    ref = dict(position=samples["position"], R=R, force=np.einsum("tij,tj->ti", R, samples["wrench"][:, :3]),
               torque=np.einsum("tij,tj->ti", R, samples["wrench"][:, 3:]), phase=samples["true_phase"],
               stamp=samples["stamp_ns"])
    return path, ref


def test_load_demonstration_matches_the_simulation(simulated_demo):
    path, ref = simulated_demo
    d = load_demonstration(path)
    T = len(ref["phase"])
    assert d["states"].shape == (T, 3) and d["forces"].shape == (T, 3) and d["phases"].shape == (T - 1,)
    assert d["path"] == str(path) and d["skipped"] == 0 and d["gaps"] == 0 and d["complete"]
    assert d["dt"] == pytest.approx(0.01)
    np.testing.assert_allclose(d["t"], ref["stamp"] * 1e-9)
    np.testing.assert_allclose(np.diff(d["t"]), 0.01, atol=1e-12)
    np.testing.assert_array_equal(d["states"], ref["position"])
    np.testing.assert_allclose(d["forces"], ref["force"], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(d["phases"], ref["phase"][1:])
    # the three valley phases, in order, each long enough to learn from
    assert list(np.unique(d["phases"])) == [0, 1, 2]
    assert np.all(np.diff(d["phases"]) >= 0)
    assert np.bincount(d["phases"]).min() > 50
    # contact shows in the force: pushed up by the plate/groove, nothing in free motion
    free, contact = d["phases"] == 0, d["phases"] > 0
    assert np.linalg.norm(d["forces"][1:][free], axis=1).mean() < 1.0
    assert np.median(d["forces"][1:][contact][:, 2]) > 1.0


def test_load_demonstration_pose_and_torque(simulated_demo):
    path, ref = simulated_demo
    d = load_demonstration(path, state="pose", features="force_torque")
    assert d["states"].shape[1] == 6 and d["forces"].shape[1] == 6
    np.testing.assert_array_equal(d["states"][:, :3], ref["position"])
    rel = Rotation.from_rotvec(d["states"][:, 3:]).as_matrix()
    # R = R_0 exp(rotvec): the rotation relative to the first sample (etar.features)
    np.testing.assert_allclose(ref["R"][0] @ rel, ref["R"], atol=1e-9)
    np.testing.assert_allclose(d["states"][0, 3:], 0.0, atol=1e-12)
    np.testing.assert_allclose(d["forces"][:, :3], ref["force"], atol=1e-12)
    np.testing.assert_allclose(d["forces"][:, 3:], ref["torque"], atol=1e-12)
    # 50 Hz keeps every other 100 Hz sample
    half = load_demonstration(path, rate_hz=50.0)
    np.testing.assert_array_equal(half["states"], ref["position"][ref["stamp"] % 20_000_000 == 0])
    with pytest.raises(RecordingError, match="state must be"):
        load_demonstration(path, state="joints")
    with pytest.raises(RecordingError, match="multiple"):
        load_demonstration(path, rate_hz=1600.0)  # 625 us: between robot cycles
    with pytest.raises(RecordingError, match="whole number of nanoseconds"):
        load_demonstration(path, rate_hz=1500.0)


def test_load_demonstration_skips_bad_messages_and_names_what_is_missing(tmp_path, simulated_demo):
    path, ref = simulated_demo
    ep = read_episode(path)
    copy = tmp_path / "copy.mcap"
    only_state = tmp_path / "state_only.mcap"
    with EpisodeWriter(copy, run_id=RUN, episode_kind="demonstration", episode_index=0) as w, \
            EpisodeWriter(only_state, run_id=RUN, episode_kind="demonstration", episode_index=0) as w2:
        for m in ep.messages:
            w.add(key(m.topic[1:]), m.payload, m.log_time_ns)
            if m.topic == "/robot/state":
                w2.add(key(m.topic[1:]), m.payload, m.log_time_ns)
        w.add(key("ft/wrench"), b'{"seq": 1, "garbage": true}', ep.messages[-1].log_time_ns + 1)
        w.add(key("robot/state"), b"\x00\x01", ep.messages[-1].log_time_ns + 2)
    assert w.bad_payloads == 2
    d = load_demonstration(copy)
    assert d["skipped"] == 2
    np.testing.assert_array_equal(d["states"], ref["position"])
    with pytest.raises(RecordingError, match="no /ft/wrench messages") as info:
        load_demonstration(only_state)
    assert str(only_state) in str(info.value)


def test_etar_cli_learns_three_phases_from_the_recording(tmp_path, simulated_demo, capsys):
    from services.cli.etar import main

    path, _ = simulated_demo
    model = tmp_path / "model.json"
    assert main(["learn", str(path), "--phases", "3", "--out", str(model), "--restarts", "1",
                 "--max-iter", "30"]) == 0
    data = json.loads(model.read_text())
    assert data["n_phases"] == 3
    assert data["metadata"]["demonstrations"] == [str(path)]
    assert len(data["metadata"]["impedance"]) == 3
    # the learned phases are the physical ones (Viterbi against the recorded labels)
    capsys.readouterr()
    assert main(["inspect", str(model), "--demos", str(path)]) == 0
    accuracy = float(re.search(r"accuracy ([0-9.]+)", capsys.readouterr().out).group(1))
    assert accuracy > 0.9
    # a broken recording is a clean command-line error naming the file
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"garbage" * 10)
    capsys.readouterr()
    assert main(["learn", str(broken), "--phases", "2", "--out", str(tmp_path / "m2.json")]) == 2
    assert str(broken) in capsys.readouterr().err


def test_etar_learn_takes_a_truncated_recording_and_says_what_it_lost(tmp_path, simulated_demo, capsys):
    from services.cli.etar import main

    path, _ = simulated_demo
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.8)])
    whole = load_demonstration(path)
    model = tmp_path / "model.json"
    assert main(["learn", str(cut), "--phases", "3", "--out", str(model), "--restarts", "1",
                 "--max-iter", "30"]) == 0
    err = capsys.readouterr().err
    assert f"warning: {cut}: incomplete recording, learning from the" in err and "no MCAP footer" in err
    n = int(re.search(r"learning from the (\d+) samples", err).group(1))
    assert 0.5 * len(whole["states"]) < n < len(whole["states"])
    assert json.loads(model.read_text())["n_phases"] == 3


def test_the_recorder_takes_episode_paths_relative_to_its_one_folder_only(tmp_path):
    from services.nodes.recorder import episode_path

    assert episode_path(tmp_path, "demonstration_00.mcap") == tmp_path / "demonstration_00.mcap"
    assert episode_path(tmp_path, "sub/reproduction_01.mcap") == tmp_path / "sub" / "reproduction_01.mcap"
    for bad in ("/abs/demonstration_00.mcap", "../escape.mcap", "a/../../b.mcap", ""):
        with pytest.raises(ValueError, match="relative to the recorder's --out-dir"):
            episode_path(tmp_path, bad)


def test_the_report_reads_past_garbage_in_a_recording_and_counts_it(tmp_path, rng):
    """What a foreign peer could publish into a run (random bytes, a seq of Infinity, a
    wrong schema) is recorded as received, and the report's reader skips it: it once
    crashed the report of a run that had reached its goal."""
    from services.results.decoding import decoded_messages, episode_links, fri_quality_series, reproduction_phases

    messages = mixed_messages(60, rng)
    garbage = [os.urandom(11), b'{"seq": Infinity, "stamp_ns": 0, "sent_ns": 0}', b'{"seq": 3}', b"[1, 2]",
               b'{"seq": 1.5, "sent_ns": 0, "stamp_ns": 0, "fri_quality": 3, "fri_state": 2}']
    messages += [(key("robot/state"), g, 5_030_000_000 + i) for i, g in enumerate(garbage)]
    write_episode(tmp_path / "g.mcap", messages)
    decoded, bad = decoded_messages(read_episode(tmp_path / "g.mcap"))
    assert bad == len(garbage)
    assert len(decoded["robot/state"]) == 60 and len(decoded["estimator/phase"]) == 6
    links = episode_links(decoded)
    assert links["robot/state"]["lost"] == 0 and links["robot/state"]["out_of_order"] == 0
    t, q, state = fri_quality_series(decoded)
    assert len(t) == 60 and set(q.tolist()) == {3} and set(state.tolist()) == {2}
    assert reproduction_phases(decoded, {1: 1})["accuracy"] == 1.0


def test_a_foreign_peers_stamp_is_counted_off_the_clock_not_taken_as_a_latency(tmp_path, rng):
    """A well-formed robot/command from a foreign peer, stamped on its own clock (sent_ns 1,
    and one from the future), is no latency of the run's: counted apart, the run's own
    latencies as they were (it once made the report's maximum 78 679 s)."""
    from services.results.decoding import decoded_messages, episode_links
    from services.results.text import link_lines

    messages = mixed_messages(40, rng)
    clean = episode_links(decoded_messages(read_episode(write_episode(tmp_path / "c.mcap", messages).path))[0])
    # recorded at a host's uptime of 78 679 s, as it was; the second stamped in the future
    for sent, at in ((1, 78_679 * 10**9), (9 * 10**18, 5_030_000_000)):
        messages.append((key("robot/command"), ROBOT_COMMAND.encode(
            **header(20, sent_ns=sent), cart_pos=rng.normal(size=12), cart_stiffness=[1000.0] * 6,
            cart_damping=[0.7] * 6, add_tcp_ft=[0.0] * 6, requested_mode=7, phase=0, estimate_seq=-1,
            goal_reached=False, hold="", episode=0), at))
    links = episode_links(decoded_messages(read_episode(write_episode(tmp_path / "f.mcap", messages).path))[0])
    assert links["robot/command"]["off_clock"] == 2 and clean["robot/command"]["off_clock"] == 0
    for figure in ("p50_us", "p99_us", "max_us", "count"):
        assert links["robot/command"][figure] == clean["robot/command"][figure]
    assert links["robot/state"]["off_clock"] == 0
    timing = {"links_publish_to_recorder": {t: v for t, v in links.items() if t == "robot/command"},
              "links_received": {"robot/command -> robot": {"latency": {}, "lost": 0, "out_of_order": 0, "bad": 0,
                                                            "off_clock": 2}}}
    text = "\n".join(link_lines(timing))
    assert "off-clock" in text and "a foreign peer's" in text
    row = [line for line in text.splitlines() if line.strip().startswith("robot/command -> robot")]
    assert row and row[0].split()[-1] == "2" and row[0].split()[3] == "-"


def test_a_topics_columns_give_back_each_message_as_added_after_a_restarted_recorders_part():
    """The report's fields per topic held as columns: iterated, every message's (log time,
    fields) in order, the known text values where they were, across a part appended."""
    from services.results.decoding import TopicColumns

    first, part = TopicColumns(("seq", "sent_ns", "phase")), TopicColumns(("seq", "sent_ns", "phase"))
    first.append(10, {"seq": 1, "sent_ns": 5, "phase": 0})
    first.append(20, {"seq": 2, "sent_ns": 6, "phase": 1, "unconditioned": "gap"})
    part.append(30, {"seq": 3, "sent_ns": 7, "phase": 2, "unconditioned": "arm_held"})
    part.append(40, {"seq": 2**63 - 1, "sent_ns": -(2**63), "phase": 1})
    first.extend(part)
    assert len(first) == 4
    assert list(first) == [(10, {"seq": 1, "sent_ns": 5, "phase": 0}),
                           (20, {"seq": 2, "sent_ns": 6, "phase": 1, "unconditioned": "gap"}),
                           (30, {"seq": 3, "sent_ns": 7, "phase": 2, "unconditioned": "arm_held"}),
                           (40, {"seq": 2**63 - 1, "sent_ns": -(2**63), "phase": 1})]


def test_the_report_counts_each_unconditioned_estimate_once_and_only_the_values_it_knows():
    from services.results.decoding import TopicColumns, reproduction_phases

    def columns(names, pairs):
        got = TopicColumns(names)
        for log_time, fields in pairs:
            got.append(log_time, fields)
        return got

    truth = [(0, {"seq": s, "sent_ns": 0, "true_phase": 0}) for s in (10, 20, 30, 40)]
    estimates = [(0, {"seq": 10, "sent_ns": 0, "phase": 0}),
                 (0, {"seq": 20, "sent_ns": 0, "phase": 0, "unconditioned": "arm_held"}),
                 (0, {"seq": 20, "sent_ns": 0, "phase": 0, "unconditioned": "arm_held"}),  # a replayed copy
                 (0, {"seq": 30, "sent_ns": 0, "phase": 0, "unconditioned": "gap"}),
                 (0, {"seq": 50, "sent_ns": 0, "phase": 0, "unconditioned": "gap"}),  # no truth: not scored
                 (0, {"seq": 40, "sent_ns": 0, "phase": 0, "unconditioned": "sideways"})]
    phases = reproduction_phases({"robot/contact": columns(("seq", "sent_ns", "true_phase"), truth),
                                  "estimator/phase": columns(("seq", "sent_ns", "phase"), estimates)}, {0: 0})
    assert phases["updates"] == 4 and phases["unconditioned"] == {"arm_held": 1, "gap": 1}
    assert reproduction_phases({}, {0: 0})["unconditioned"] == {"arm_held": 0, "gap": 0}



def test_interrupts_in_the_hand_over_to_the_writer_process_lose_nothing_and_corrupt_nothing(tmp_path):
    """An in-process run's Ctrl-C is a KeyboardInterrupt raised wherever the run is.  Raised
    100 times while messages go to the MCAP writer's helper process (big payloads,
    so each hand-over blocks on the pipe): every add that returned is in the finished file
    once; none is there twice; the file reads back complete."""
    import threading
    import time

    from services.recordings.offload import WriterProcess

    def interrupt(signum, frame):
        if armed[0]:
            armed[0] = False
            raise KeyboardInterrupt
        # it landed between two adds or after the last: raised there, it would leave the test
        # (and end pytest's session).  Only a flag: a handler that takes a lock (an Event's)
        # that the code it interrupted holds waits for ever
        missed[0] = True

    process = WriterProcess()
    writer = process.open(tmp_path / "e.mcap", run_id=RUN, episode_kind="demonstration", episode_index=0)
    payload = RUNNER_EVENT.encode(**header(0), event="episode_end", stage="demonstrate", episode=0,
                                  info={"note": "x" * 2000})
    added, caught, done = [], threading.Event(), threading.Event()
    armed, missed = [False], [False]  # plain flags, set and read without a lock (see interrupt)

    def interrupter():  # one Ctrl-C at a time: a second before the first is met is the way out of a hang
        rng = np.random.default_rng(3)
        while not done.is_set():
            time.sleep(rng.uniform(0, 0.002))
            os.kill(os.getpid(), signal.SIGINT)
            while not caught.wait(0.05) and not done.is_set():
                pass
            caught.clear()

    before = signal.signal(signal.SIGINT, interrupt)
    thread = threading.Thread(target=interrupter, daemon=True)
    interrupted, seq = 0, 0
    try:
        thread.start()
        while interrupted < 100:
            try:
                armed[0] = True
                writer.add(key(RUNNER_EVENT.topic), payload, 1_000_000 + seq)
                armed[0] = False
                added.append(1_000_000 + seq)
            except KeyboardInterrupt:
                interrupted += 1
                caught.set()
            if missed[0]:  # the interrupter waits to be told before it sends the next
                missed[0] = False
                caught.set()
            seq += 1
    finally:
        done.set()
        thread.join()
        signal.signal(signal.SIGINT, before)
    writer.finish()
    process.close()
    assert len(added) > 2 * WriterProcess.BATCH, len(added)
    episode = read_episode(tmp_path / "e.mcap")
    logged = [m.log_time_ns for m in episode.messages]
    assert episode.complete, episode.problem
    assert logged == sorted(set(logged)), "a message recorded twice"
    assert set(added) <= set(logged), f"{len(set(added) - set(logged))} added messages missing"


def test_what_the_writer_process_prints_does_not_reach_its_replies(tmp_path, monkeypatch):
    """The helper's replies have a pipe of their own: what it prints (numba writes a line per
    cached kernel its imports load when NUMBA_DEBUG_CACHE is set) goes to stderr, and the
    episode's file is written whole.  On stdout, those lines broke the first reply."""
    from services.recordings.offload import WriterProcess

    monkeypatch.setenv("NUMBA_DEBUG_CACHE", "1")
    process = WriterProcess()
    try:
        writer = process.open(tmp_path / "e.mcap", run_id=RUN, episode_kind="demonstration", episode_index=0)
        for seq in range(3):
            writer.add(key(RUNNER_EVENT.topic),
                       RUNNER_EVENT.encode(**header(seq), event="episode_end", stage="demonstrate", episode=0,
                                           info={}), 1_000_000 + seq)
        writer.finish()
    finally:
        process.close()
    episode = read_episode(tmp_path / "e.mcap")
    assert episode.complete, episode.problem
    assert [m.log_time_ns for m in episode.messages] == [1_000_000, 1_000_001, 1_000_002]
    assert writer.messages_written == 3
