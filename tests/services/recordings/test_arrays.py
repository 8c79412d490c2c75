"""A recording as numpy arrays for notebooks (services/recordings/arrays.py): one array per
field, first axis the message, against what was written; and on a real demonstration, the
arrays' lengths against the messages the recording holds."""

from __future__ import annotations

import json
import sys
import types
from collections import Counter

import numpy as np
import pytest

from services.recordings.arrays import (TIME_FIELDS, TruncatedRecordingWarning, recording_arrays, topic_arrays,
                                       topic_frame)
from services.recordings.format import RecordingError
from services.recordings.reader import read_episode
from services.recordings.writer import EpisodeWriter
from services.runtime.messages import (EPISODE_SUMMARY, ESTIMATOR_PHASE, FT_WRENCH, ROBOT_CONTACT, ROBOT_STATE,
                                       RUNNER_EVENT)
from services.scenario import Scenario
from tests.support import run, scenario

RUN = "arrays"
N = 30  # robot cycles written


def key(topic: str) -> str:
    return f"etar/{RUN}/{topic}"


def head(seq: int) -> dict:
    return dict(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=7_000_000_000 + seq)


def pose(seq: int) -> list:
    return [1.0, 0.0, 0.0, 0.5 + seq * 1e-3, 0.0, 1.0, 0.0, -0.06, 0.0, 0.0, 1.0, 0.3]


@pytest.fixture
def recording(tmp_path):
    """N cycles of robot_state, robot_contact and ft_wrench, an estimate every tenth cycle
    (its posterior of 2, then 3 entries), a runner event with a nested object, a visual
    status without a definition, one payload that is not JSON, and the episode summary."""
    path = tmp_path / "tiny.mcap"
    with EpisodeWriter(path, run_id=RUN, episode_kind="demonstration", episode_index=0) as w:
        w.add(key("runner/event"), RUNNER_EVENT.encode(**head(0), event="episode_begin", stage="demonstrate",
                                                       episode=0, info={"start": [0.6, -0.06, 0.3],
                                                                        "seeds": {"teacher": 3}}), 1)
        for seq in range(1, N + 1):
            t = 1_000_000_000 + seq * 1_000_000
            w.add(key("robot/state"), ROBOT_STATE.encode(
                **head(seq), reflected_seq=-1, fri_state=1, fri_quality=0, control_mode=2,
                msr_jnt_pos=[0.01 * seq] * 7, msr_cart_pos=pose(seq), est_ext_tcp_ft=[0.0] * 6, answer_rate=0.0,
                latency_s=0.0, jitter_s=0.0, miss_rate=1.0, safety=0, gravity_compensation=True, episode=0), t)
            w.add(key("robot/contact"), ROBOT_CONTACT.encode(
                **head(seq), wrench=[0.0] * 6, contact_force=[0.0, 0.0, -float(seq)],
                touching=["plate_left"] if seq > 20 else [], true_phase=int(seq > 20), episode=0), t + 1)
            w.add(key("ft/wrench"), FT_WRENCH.encode(
                **head(seq), rdt_sequence=seq, ft_sequence=seq, status=0, counts=[seq, 0, 0, 0, 0, -seq],
                counts_per_force=1e6, counts_per_torque=1e6, wrench=[seq * 1e-6, 0, 0, 0, 0, 0]), t + 2)
            if seq % 10 == 0:
                posterior = [0.25, 0.75] if seq == 10 else [0.2, 0.3, 0.5]
                w.add(key("estimator/phase"), ESTIMATOR_PHASE.encode(
                    **head(seq), posterior=posterior, phase=len(posterior) - 1, input_seq=seq, ft_seq=seq, episode=0,
                    **({"input_fault": "wrench_saturated"} if seq == 30 else {})), t + 3)
            if seq % 10 == 5:
                w.add("/viz/status", json.dumps({"timestamp": {"sec": 0, "nsec": seq * 1_000_000}, "seq": seq,
                                                 "force": [0.0, 0.0, float(seq)], "phase": -1 if seq < 20 else 1,
                                                 **({"hold": "x"} if seq == 25 else {})}).encode(), t + 4)
        w.add(key("ft/wrench"), b"{not json", 1_000_000_000 + (N + 1) * 1_000_000)
        w.add(key("robot/episode"), EPISODE_SUMMARY.encode(
            **head(N), episode=0, kind="demonstration", reason="teacher_done", first_seq=1, last_seq=N,
            sim_seconds=N / 1000, wall_seconds=0.1, final_position=[0.53, -0.06, 0.3], peak_contact_force=float(N),
            safety=0, missed_answers=0, fri={"answered": 0, "missed": N},
            loop={"cycles": N, "lateness": {"p99_us": 1.5}}), 2_000_000_000)
    return path


def test_topic_arrays_one_row_per_message_in_the_declared_types(recording):
    st = topic_arrays(recording, "/robot/state")
    assert set(TIME_FIELDS) <= set(st) and list(st)[2:5] == ["seq", "stamp_ns", "sent_ns"]
    assert all(len(v) == N for v in st.values())
    np.testing.assert_array_equal(st["seq"], np.arange(1, N + 1))
    assert st["seq"].dtype == np.int64 and st["sent_ns"][0] == 7_000_000_001  # exact, not float
    assert st["msr_cart_pos"].shape == (N, 12) and st["msr_cart_pos"].dtype == np.float64
    np.testing.assert_array_equal(st["msr_cart_pos"][:, 3], [0.5 + s * 1e-3 for s in range(1, N + 1)])
    assert st["msr_jnt_pos"].shape == (N, 7) and st["gravity_compensation"].dtype == np.bool_
    assert st["answer_rate"].dtype == np.float64 and st["log_time_ns"][0] == 1_001_000_000
    # the leading slash is optional
    np.testing.assert_array_equal(topic_arrays(recording, "robot/state")["seq"], st["seq"])

    contact = topic_arrays(recording, "robot/contact")
    assert contact["touching"].dtype == object and contact["touching"][0] == [] \
        and contact["touching"][-1] == ["plate_left"]
    assert contact["contact_force"].shape == (N, 3) and contact["true_phase"].sum() == 10

    est = topic_arrays(recording, "/estimator/phase")
    # a posterior of 2 then of 3 phases: padded with NaN
    assert est["posterior"].shape == (3, 3) and np.isnan(est["posterior"][0, 2])
    np.testing.assert_array_equal(est["posterior"][1], [0.2, 0.3, 0.5])
    assert list(est["input_fault"]) == [None, None, "wrench_saturated"]  # optional: absent where not sent

    ev = topic_arrays(recording, "/runner/event")
    assert ev["info.start"].shape == (1, 3) and ev["info.seeds.teacher"].tolist() == [3]
    summary = topic_arrays(recording, "/robot/episode")
    assert summary["fri.missed"].tolist() == [N] and summary["loop.lateness.p99_us"].tolist() == [1.5]
    assert summary["final_position"].shape == (1, 3) and summary["reason"].tolist() == ["teacher_done"]
    assert np.isnan(summary["goal_reached_at_s"][0])  # optional, not sent

    # a topic without a definition: the types read from the values
    viz = topic_arrays(recording, "/viz/status")
    assert viz["timestamp.nsec"].dtype == np.int64 and viz["force"].shape == (3, 3)
    assert viz["phase"].tolist() == [-1, -1, 1] and viz["hold"].tolist() == [None, None, "x"]


def test_a_payload_that_does_not_decode_raises_naming_it_or_is_skipped(recording):
    with pytest.raises(RecordingError, match=r"tiny.mcap: /ft/wrench message 30 .* does not decode"):
        topic_arrays(recording, "/ft/wrench")
    ft = topic_arrays(recording, "/ft/wrench", skip_bad=True)
    assert ft["counts"].shape == (N, 6) and ft["counts"].dtype == np.int64 and ft["wrench"].shape == (N, 6)
    with pytest.raises(RecordingError, match=r"tiny.mcap: no topic '/robot/command' in this recording \(topics: "):
        topic_arrays(recording, "/robot/command")
    with pytest.raises(RecordingError, match="no such file"):
        topic_arrays(recording.with_name("missing.mcap"), "/robot/state")


def test_recording_arrays_every_topic_once(recording):
    arrays = recording_arrays(recording, skip_bad=True)
    counts = Counter(m.topic for m in read_episode(recording).messages)
    counts["/ft/wrench"] -= 1  # the payload that is not JSON
    assert {t: len(a["log_time_ns"]) for t, a in arrays.items()} == dict(counts)
    np.testing.assert_array_equal(arrays["/robot/state"]["msr_cart_pos"],
                                  topic_arrays(recording, "/robot/state")["msr_cart_pos"])


def test_a_truncated_recording_gives_its_rows_with_a_warning_that_says_so(recording, tmp_path):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a finished file: no warning
        whole = topic_arrays(recording, "/robot/state")
    data = recording.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) - 200])  # the summary and the footer gone, the chunks whole
    with pytest.warns(TruncatedRecordingWarning, match=r"cut.mcap: a truncated recording .*: the arrays hold the"):
        rows = topic_arrays(cut, "/robot/state")
    np.testing.assert_array_equal(rows["seq"], whole["seq"][: len(rows["seq"])])
    with pytest.warns(TruncatedRecordingWarning):
        recording_arrays(cut, skip_bad=True)


def test_topic_frame_needs_pandas_and_says_so(recording, monkeypatch):
    monkeypatch.setitem(sys.modules, "pandas", None)  # import pandas raises ImportError
    with pytest.raises(ImportError, match="topic_frame needs pandas, which the testbench does not install"):
        topic_frame(recording, "/robot/state")


def test_topic_frame_columns(recording, monkeypatch):
    """With pandas (a stand-in here if it is not installed: it is not a dependency), a 2-D
    field becomes one column per entry."""
    try:
        import pandas
    except ImportError:
        pandas = types.SimpleNamespace(DataFrame=lambda columns: columns)
        monkeypatch.setitem(sys.modules, "pandas", pandas)
    frame = topic_frame(recording, "/robot/state")
    columns = list(frame.keys())
    assert "msr_cart_pos[0]" in columns and "msr_cart_pos[11]" in columns and "msr_cart_pos" not in columns
    assert len(frame["seq"]) == N and list(frame["msr_cart_pos[3]"]) == [0.5 + s * 1e-3 for s in range(1, N + 1)]


@pytest.mark.slow
def test_arrays_of_a_real_demonstration_have_one_row_per_message(tmp_path):
    described = scenario("smoke").described()
    demo = dict(described, stages=[{"demonstrate": dict(described["stages"][0]["demonstrate"], count=1)}])
    report = run(Scenario.from_dict(demo), tmp_path / "run", progress=lambda line: None, transport="inproc")
    assert report["error"] is None, report["error"]
    path = tmp_path / "run" / report["demonstrations"][0]["path"]
    counts = Counter(m.topic for m in read_episode(path).messages)
    arrays = recording_arrays(path)
    assert set(arrays) == set(counts) and {"/robot/state", "/ft/wrench", "/teacher/wrench"} <= set(arrays)
    for topic, fields in arrays.items():
        for name, values in fields.items():
            assert values.shape[0] == counts[topic], (topic, name)
    st = arrays["/robot/state"]
    assert st["msr_cart_pos"].shape == (counts["/robot/state"], 12) and np.all(np.diff(st["seq"]) == 1)
    assert np.all(np.isfinite(st["msr_cart_pos"]))
