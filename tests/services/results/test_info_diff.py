"""``etar-bench info`` and ``etar-bench diff`` as functions: a recording and a run folder
described (services/results/info/), two runs compared (services/results/diff.py).

Fast: small recordings written here with the recorder's writer, with a known gap, a known
episode summary and known code metadata.  Slow: three smoke runs in one process, two of
one seed (different run ids) and one of another seed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from mcap.reader import make_reader

from services.recordings.format import RecordingError
from services.recordings.reader import recorded_content
from services.recordings.writer import EpisodeWriter
from services.results.diff import IGNORED, IGNORED_TEXT, DiffError, diff_runs, recording_content
from services.results.folder import RunFolderError
from services.results.info import InfoError, describe, info_text
from services.runtime.provenance import code, code_text
from services.runtime.messages import (EPISODE_SUMMARY, ESTIMATOR_PHASE, FT_WRENCH, ROBOT_STATE, RUNNER_EVENT,
                                       SERVICE_LOG)
from tests.support import run, scenario

SCENARIO = "name: tiny\nworld: valley\nclock: lockstep\nseed: 7\nstages:\n  - demonstrate: {count: 1}\n"
CODE = {"version": "0.1.0", "commit": "0123456789abcdef", "dirty": "True"}
MISSING = (50, 51, 52)  # robot cycles the hand-written recording lacks


def state(seq: int, sent_ns: int, x: float = 0.5) -> bytes:
    return ROBOT_STATE.encode(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=sent_ns, reflected_seq=seq - 1, fri_state=2,
                              fri_quality=3, control_mode=2, msr_jnt_pos=[0.1 * i for i in range(7)],
                              msr_cart_pos=[1.0, 0, 0, x, 0, 1.0, 0, 0.0, 0, 0, 1.0, 0.3],
                              est_ext_tcp_ft=[0.0] * 6, answer_rate=1.0, latency_s=2e-4, jitter_s=1e-5,
                              miss_rate=0.0, safety=0, gravity_compensation=False, episode=0)


def write_recording(path: Path, run_id: str, *, cycles: int = 100, sent_offset: int = 0,
                    change: int | None = None) -> Path:
    """A reproduction of ``cycles`` robot cycles (without ``MISSING``): robot_state and
    ft_wrench every cycle, the estimator every tenth, a runner event, a log line, a visual
    status and the episode summary; robot_state of cycle ``change`` with another x."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with EpisodeWriter(path, run_id=run_id, episode_kind="reproduction", episode_index=0, scenario_text=SCENARIO,
                       metadata={"start": "[0.6, -0.06, 0.3]"}) as w:

        def key(topic: str) -> str:
            return f"etar/{run_id}/{topic}"

        w.add(key("runner/event"), RUNNER_EVENT.encode(seq=0, stamp_ns=0, sent_ns=1 + sent_offset,
                                                       event="episode_begin", stage="reproduce", episode=0,
                                                       info={"run": run_id}), 10)
        for seq in range(1, cycles + 1):
            if seq in MISSING:
                continue
            t = 5_000_000_000 + seq * 1_000_000
            sent = 1_000_000_000 + seq * 1000 + sent_offset
            w.add(key("robot/state"), state(seq, sent, 0.7 if seq == change else 0.5), t)
            w.add(key("ft/wrench"), FT_WRENCH.encode(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=sent, rdt_sequence=seq,
                                                     ft_sequence=seq, status=0, counts=[0, 0, 1000, 0, 0, 0],
                                                     counts_per_force=1e6, counts_per_torque=1e6,
                                                     wrench=[0.0, 0.0, 0.001, 0.0, 0.0, 0.0]), t + 10)
            if seq % 10 == 0:
                w.add(key("estimator/phase"), ESTIMATOR_PHASE.encode(
                    seq=seq, stamp_ns=seq * 1_000_000, sent_ns=sent, posterior=[0.2, 0.8], phase=1, input_seq=seq,
                    ft_seq=seq, episode=0), t + 20)
            if seq == 20:
                w.add("/viz/status", json.dumps({"seq": seq, "timestamp": {"sec": 0, "nsec": 20_000_000},
                                                 "sent": sent}).encode(), t + 30)
                w.add(key("service/log"), SERVICE_LOG.encode(seq=1, stamp_ns=0, sent_ns=sent, role="robot", level=2,
                                                             text=f"hello from {run_id}"), t + 40)
        w.add(key("robot/episode"), EPISODE_SUMMARY.encode(
            seq=cycles, stamp_ns=cycles * 1_000_000, sent_ns=2_000_000_000 + sent_offset, episode=0,
            kind="reproduction", reason="goal_reached", first_seq=1, last_seq=cycles, sim_seconds=cycles / 1000,
            wall_seconds=0.5 + sent_offset, final_position=[0.57, 0.0, 0.21], peak_contact_force=12.5, safety=0,
            missed_answers=0, goal_reached_at_s=0.09, fri={"answered": cycles}, loop={"cycles": cycles}),
            6_000_000_000)
    return path


def make_run(folder: Path, run_id: str, **kwargs) -> Path:
    """A run folder as the runner leaves it, cut to what info and diff read."""
    write_recording(folder / "recordings" / "reproduction_00.mcap", run_id, **kwargs)
    report = {"scenario": "tiny", "source": "tiny.yaml", "run_id": run_id, "error": None, "wall_seconds": 1.5,
              "transport": "inproc", "environment": {"clock": "lockstep"},
              "provenance": dict(CODE, dirty=False, date="2026-12-02T10:00:00+00:00", command="etar-bench run tiny"),
              "demonstrations": [],
              "learning": {"model": None, "selection": {"criterion": "fixed", "best": 3}},
              "reproductions": [{"index": 0, "path": "recordings/reproduction_00.mcap", "reason": "goal_reached",
                                 "success": True, "sim_seconds": 0.1, "wall_seconds": 0.5,
                                 "peak_contact_force": 12.5, "phases": {"accuracy": 0.95}}],
              "summary": {"phases_chosen": 3, "reproductions": 1, "successes": 1, "online_phase_accuracy": 0.95,
                          "episode_wall_seconds": 0.5 + kwargs.get("sent_offset", 0), "by_model": {}}}
    (folder / "report.json").write_text(json.dumps(report))
    (folder / "scenario.yaml").write_text(SCENARIO)
    return folder


# ---------------------------------------------------------------------------
# info, fast
# ---------------------------------------------------------------------------


def test_info_of_a_recording_names_its_episode_topics_rates_gaps_and_result(tmp_path):
    path = write_recording(tmp_path / "recordings" / "reproduction_00.mcap", "r1")
    d = describe(path)
    json.dumps(d, allow_nan=False)  # strict JSON
    assert d["kind"] == "recording" and d["complete"] and d["problem"] is None
    assert d["size_bytes"] == path.stat().st_size and d["mcap"]["library"].startswith("etar-testbench")
    assert d["run_id"] == "r1" and d["episode"] == {"kind": "reproduction", "index": 0}
    assert d["scenario"]["name"] == "tiny" and d["scenario"]["seed"] == 7
    assert d["code"] == code() and d["metadata"] == {"start": "[0.6, -0.06, 0.3]"}  # the writer's own code
    # cycles 1..100: 100 ms of simulated time, whatever the receive times
    assert d["simulated"]["seconds"] == pytest.approx(0.100)
    topics = {t["topic"]: t for t in d["topics"]}
    assert set(topics) == {"/robot/state", "/ft/wrench", "/estimator/phase", "/runner/event", "/robot/episode",
                           "/service/log", "/viz/status"}
    st = topics["/robot/state"]
    assert st["schema"] == "robot_state" and st["messages"] == 97 and st["nominal_hz"] == 1000
    assert st["rate_hz"] == pytest.approx(970)
    assert st["gaps"] == {"missing": 3, "duplicates": 0, "gaps": 1, "largest_gap_s": 0.004,
                          "largest_gap_periods": 4.0, "largest_gap_ends_at_seq": 53}
    est = topics["/estimator/phase"]
    # the estimator of cycle 50 went with its cycle: one missing of ten
    assert est["messages"] == 9 and est["nominal_hz"] == 100 and est["gaps"]["missing"] == 1
    assert topics["/runner/event"]["gaps"] is None and topics["/viz/status"]["schema"] == "etar.VisualStatus"
    r = d["result"]
    assert r["reason"] == "goal_reached" and r["goal_reached"] and r["goal_reached_at_s"] == 0.09
    # in a run folder without a report: the episode summary alone
    assert r["source"] == "episode summary"

    text = info_text(d)
    print(text)
    assert "run       r1, reproduction 0" in text and "tiny, seed 7" in text and f"code      {code_text()}" in text
    assert "goal_reached after 0.100 s simulated" in text
    line = next(x for x in text.splitlines() if x.strip().startswith("/robot/state"))
    assert line.split()[2:6] == ["97", "970.0", "1000", "3"]


def test_info_of_a_run_folder_and_its_report_verdict(tmp_path):
    run_dir = make_run(tmp_path / "run", "r1")
    d = describe(run_dir)
    json.dumps(d, allow_nan=False)
    assert d["kind"] == "run" and d["run_id"] == "r1" and d["transport"] == "inproc" and d["clock"] == "lockstep"
    assert d["scenario"]["name"] == "tiny" and d["scenario"]["seed"] == 7 and d["scenario"]["from"] == "scenario.yaml"
    assert d["provenance"]["commit"] == CODE["commit"] and d["summary"]["successes"] == 1
    assert d["model"]["phases_chosen"] == 3 and d["model"]["criterion"] == "fixed"
    (ep,) = d["episodes"]
    n = sum(1 for _ in _messages(run_dir / "recordings" / "reproduction_00.mcap"))
    assert ep["kind"] == "reproduction" and ep["index"] == 0 and ep["success"] and ep["messages"] == n
    assert ep["complete"] and d["totals"]["messages"] == n and d["totals"]["episodes"] == 1
    text = info_text(d)
    print(text)
    assert "run id    r1" in text and "1 of 1 reproductions succeeded" in text and "code      0.1.0 (git" in text
    # the recording in the run folder gets the report's verdict, and says it has no code version
    rec = describe(run_dir / "recordings" / "reproduction_00.mcap")
    assert rec["result"]["success"] is True and rec["result"]["phase_accuracy"] == 0.95
    assert rec["result"]["source"] == "episode summary + report.json"
    assert rec["code"] == code() and f"code      {code_text()}" in info_text(rec)
    assert describe(run_dir / "report.json")["kind"] == "run"


def test_info_of_a_cut_recording_and_a_run_folder_without_report(tmp_path, capsys):
    run_dir = tmp_path / "cut"
    full = write_recording(tmp_path / "full.mcap", "r1", cycles=3000)
    data = full.read_bytes()
    (run_dir / "recordings").mkdir(parents=True)
    cut = run_dir / "recordings" / "reproduction_00.mcap"
    cut.write_bytes(data[:len(data) * 2 // 3])  # a recorder killed mid-episode
    d = describe(cut)
    assert not d["complete"] and "no MCAP footer" in d["problem"] and d["result"] is None
    assert "INCOMPLETE" in info_text(d) and "none recorded" in info_text(d)
    r = describe(run_dir)
    (ep,) = r["episodes"]
    assert not r["report"] and not ep["complete"] and ep["kind"] == "reproduction" and ep["messages"] > 0
    assert r["totals"]["incomplete"] == 1 and "no report.json" in info_text(r)
    # the command describes them all the same, and says in its exit code that not all is well
    from services.cli import bench as bench_cli
    assert bench_cli.main(["info", str(cut)]) == 1
    assert bench_cli.main(["info", str(run_dir)]) == 1
    assert bench_cli.main(["info", str(full)]) == 0
    # a recorder restarted mid-episode: its first part cut by design, the next part finished
    parts = make_run(tmp_path / "parts", "r-p")
    first = parts / "recordings" / "reproduction_00.mcap"
    (parts / "recordings" / "reproduction_00.part2.mcap").write_bytes(first.read_bytes())
    first.write_bytes(data[:len(data) // 3])
    report = json.loads((parts / "report.json").read_text())
    report["reproductions"][0]["recording_parts"] = ["recordings/reproduction_00.part2.mcap"]
    (parts / "report.json").write_text(json.dumps(report))
    (ep,) = describe(parts)["episodes"]
    assert ep["complete"] and len(ep["files"]) == 2
    assert bench_cli.main(["info", str(parts)]) == 0
    kept = make_run(tmp_path / "summary", "r-s")
    (kept / "recordings" / "reproduction_00.mcap").unlink()  # lost
    assert bench_cli.main(["info", str(kept)]) == 1
    shutil.rmtree(kept / "recordings")  # none kept, by choice (a sweep's --record summary)
    capsys.readouterr()
    assert bench_cli.main(["info", str(kept)]) == 0
    said = capsys.readouterr().out
    assert "not kept: the run has no recordings/" in said and "INCOMPLETE" not in said and " incomplete" not in said


def test_info_errors_name_the_path(tmp_path):
    with pytest.raises(InfoError, match="nowhere: no such file or folder"):
        describe(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InfoError, match="not a run folder"):
        describe(tmp_path / "empty")
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording at all, just some text\n")
    with pytest.raises(RecordingError, match="notes.mcap: not a readable MCAP file"):
        describe(text)
    good = write_recording(tmp_path / "good.mcap", "r1", cycles=2000)
    with open(good, "rb") as f:
        chunk = make_reader(f).get_summary().chunk_indexes[0]
    data = bytearray(good.read_bytes())
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle:middle + 64] = bytes(64)  # damage inside a chunk of a finished file
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="bad.mcap: corrupt MCAP file") as err:
        describe(bad)
    assert "\n" not in str(err.value)
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "report.json").write_text("{not json")
    with pytest.raises(RunFolderError, match="report.json: not a JSON report"):
        describe(tmp_path / "broken")


# ---------------------------------------------------------------------------
# diff, fast
# ---------------------------------------------------------------------------


def test_diff_ignores_run_id_sent_ns_wall_clock_and_visual_topics(tmp_path):
    a = make_run(tmp_path / "a", "run-a")
    b = make_run(tmp_path / "b", "run-b", sent_offset=12345)  # other run id, publish times, wall seconds
    d = diff_runs(a, b)
    print(d.text())
    assert d.same and d.content_same and d.results_same and d.first_difference is None
    (f,) = d.files
    assert f.messages_a == f.messages_b == 97 * 2 + 9  # robot_state, ft_wrench, estimator
    assert {r.name for r in d.rows if r.a != r.b} == {"run_id", "summary.episode_wall_seconds"}
    assert not any(r.differs for r in d.rows)
    assert d.text().splitlines()[2].startswith("SAME") and IGNORED_TEXT in d.text()
    assert any("sent_ns" in x for x in IGNORED) and any("run id" in x for x in IGNORED)
    assert any("/viz/status" in x for x in IGNORED) and any("/robot/episode" in x for x in IGNORED)
    out = d.to_dict()
    json.dumps(out, allow_nan=False)
    assert out["same"] and out["files"][0]["same"] and out["ignored"] == list(IGNORED)



def test_diff_compares_the_runs_models(tmp_path):
    """model.json is what a run learned: two runs whose models differ are not the same, even
    with the same recordings; the fit's wall-clock seconds and the note of what made it are
    not compared."""
    a = make_run(tmp_path / "a", "run-a")
    b = make_run(tmp_path / "b", "run-b")
    model = {"format": "etar-model", "parameters": {"A": [[1.0, 0.0]]}, "fit": {"seconds": 1.5, "seed": 0},
             "metadata": {"made_by": "a"}}
    (a / "model.json").write_text(json.dumps(model))
    (b / "model.json").write_text(json.dumps(dict(model, fit={"seconds": 9.0, "seed": 0},
                                                  metadata={"made_by": "b"})))
    assert diff_runs(a, b).same
    (b / "model.json").write_text(json.dumps(dict(model, parameters={"A": [[1.0, 1e-9]]})))
    d = diff_runs(a, b)
    assert d.content_same and not d.results_same and not d.same
    assert d.first_difference.startswith("model.json: sha256 "), d.first_difference
    assert "DIFFERENT (the results)" in d.text()
    (b / "model.json").unlink()
    assert diff_runs(a, b).first_difference.endswith("in A, - in B")

def test_diff_compares_what_a_foreign_peer_published_into_a_run(tmp_path):
    """The recorder keeps every payload on the run's topics, a foreign peer's too: garbage, JSON
    with a seq of any kind, duplicates.  diff compares them as bytes (seq -1) and names them."""
    a = make_run(tmp_path / "a", "run-a")
    b = make_run(tmp_path / "b", "run-b")
    path = b / "recordings" / "demonstration_00.mcap"
    shutil.copy(a / "recordings" / "reproduction_00.mcap", a / "recordings" / "demonstration_00.mcap")
    foreign = [b"{not json", b'{"seq": "x"}', b'{"seq": null}', b'{"seq": 1.5}', b'{"seq": true}', b"[]", b"",
               b"[" * 100_000,  # nested past the JSON parser's recursion
               state(7, 99)]  # and cycle 7's state again, as A has it but for its publish time
    with EpisodeWriter(path, run_id="run-b", episode_kind="reproduction", episode_index=0, scenario_text=SCENARIO,
                       metadata={"start": "[0.6, -0.06, 0.3]"}) as w:
        for i, payload in enumerate(foreign):
            w.add("etar/run-b/robot/state", payload, 1_000 + i)
    d = diff_runs(a, b)
    print(d.text())
    assert not d.content_same
    f = next(f for f in d.files if f.name == "demonstration_00.mcap")
    assert f.messages_b == len(foreign) and f.only_b == 1 and f.changed == 0  # the garbage at seq -1; cycle 7 same
    assert f.first == "demonstration_00.mcap /robot/state seq -1: only in B"
    assert sorted(recorded_content(b)["demonstration_00.mcap"])[0][1] == -1


def test_diff_names_the_first_message_that_differs_and_a_file_only_one_run_has(tmp_path):
    a = make_run(tmp_path / "a", "run-a")
    b = make_run(tmp_path / "b", "run-b", change=42)
    d = diff_runs(a, b)
    print(d.text())
    assert not d.same and not d.content_same and d.results_same
    assert d.first_difference == ("reproduction_00.mcap /robot/state seq 42: msr_cart_pos[3]: 0.5 in A, 0.7 in B "
                                  "(1 of 12 entries differ)")
    assert d.files[0].changed == 1 and d.files[0].only_a == d.files[0].only_b == 0
    # a run with one more recording: that file is the difference it names first
    shutil.copy(a / "recordings" / "reproduction_00.mcap", a / "recordings" / "demonstration_00.mcap")
    d = diff_runs(a, b)
    assert d.first_difference == f"demonstration_00.mcap: only in A ({a})"
    assert "demonstration_00.mcap  only in A" in d.text()
    # a cycle one run lacks
    c = make_run(tmp_path / "c", "run-c", cycles=99)
    d = diff_runs(b, c)
    assert d.first_difference.startswith("reproduction_00.mcap /robot/state seq 42: msr_cart_pos[3]")
    assert d.files[0].only_a == 3 and d.files[0].changed == 1  # cycle 100's state, wrench, estimate
    # the same content, another result: the result is what it names
    e = make_run(tmp_path / "e", "run-e")
    report = json.loads((e / "report.json").read_text())
    report["summary"]["successes"] = 0
    (e / "report.json").write_text(json.dumps(report))
    d = diff_runs(tmp_path / "a", e)
    assert d.first_difference.startswith("demonstration_00.mcap: only in A")
    d = diff_runs(make_run(tmp_path / "f", "run-f"), e)
    assert d.content_same and not d.same and d.first_difference == "report.json summary.successes: 1 in A, 0 in B"
    assert "summary.successes" in d.results_table and "differs" in d.results_table


def test_diff_refuses_what_is_not_a_run_folder(tmp_path):
    a = make_run(tmp_path / "a", "run-a")
    with pytest.raises(DiffError, match="nowhere: no such folder"):
        diff_runs(a, tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DiffError, match="empty: not a run folder"):
        diff_runs(tmp_path / "empty", a)
    with pytest.raises(DiffError, match="a file; diff compares two run folders"):
        diff_runs(a, a / "report.json")


def test_diff_of_runs_that_lost_what_they_recorded_is_trouble_not_same(tmp_path):
    """Two runs that both lost the recordings their reports name, or both hold an unreadable
    model, compared nothing: not SAME but trouble (DiffError: exit 2), naming the file."""
    a = make_run(tmp_path / "a", "run-a")
    b = make_run(tmp_path / "b", "run-b")
    for run in (a, b):
        (run / "recordings" / "reproduction_00.mcap").unlink()
    with pytest.raises(DiffError, match=r"reproduction_00.mcap: named by .*report.json \(reproductions\), missing"):
        diff_runs(a, b)
    for run in (a, b):  # no recordings/ at all: kept by choice (a sweep's --record summary): the results
        shutil.rmtree(run / "recordings")
    d = diff_runs(a, b)
    assert d.files == [] and d.same and "none in either run" in d.text()
    for run in (a, b):
        (run / "recordings").write_text("not a folder")
    with pytest.raises(DiffError, match="recordings: not a folder"):
        diff_runs(a, b)
    c, d = make_run(tmp_path / "c", "run-c"), make_run(tmp_path / "d", "run-d")
    for run in (c, d):
        (run / "model.json").write_text("{garbage")
    with pytest.raises(DiffError, match=r"model.json: not a JSON model \(JSONDecodeError"):
        diff_runs(c, d)

def _messages(path):
    from services.recordings.reader import read_episode

    return read_episode(path).messages


# ---------------------------------------------------------------------------
# real runs
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Three smoke runs in one process: a and b of seed 0 under different run ids, c of seed 1."""
    base = tmp_path_factory.mktemp("info_diff")
    out = {}
    for name, value in (("a", scenario("smoke")), ("b", scenario("smoke")), ("c", scenario("smoke", {"seed": 1}))):
        report = run(value, base / name, progress=lambda line: None, transport="inproc", run_id=f"infodiff-{name}")
        assert report["error"] is None, report["error"]
        out[name] = base / name
    return out


@pytest.mark.slow
def test_info_of_a_smoke_run_and_its_recordings(runs):
    report = json.loads((runs["a"] / "report.json").read_text())
    d = describe(runs["a"])
    json.dumps(d, allow_nan=False)
    print(info_text(d))
    assert d["run_id"] == "infodiff-a" and d["scenario"]["name"] == "smoke" and d["scenario"]["seed"] == 0
    assert d["summary"] == report["summary"] and d["error"] is None
    if "provenance" in report:
        assert d["provenance"] == report["provenance"]
    assert [(e["kind"], e["index"]) for e in d["episodes"]] == [("demonstration", 0), ("demonstration", 1),
                                                                ("reproduction", 0)]
    assert d["model"]["models"][0]["phases"] == 3
    counts = [len(_messages(runs["a"] / e["files"][0])) for e in d["episodes"]]
    assert [e["messages"] for e in d["episodes"]] == counts and d["totals"]["messages"] == sum(counts)
    assert all(e["complete"] for e in d["episodes"]) and d["episodes"][2]["success"] is True

    rec = describe(runs["a"] / "recordings" / "reproduction_00.mcap")
    json.dumps(rec, allow_nan=False)
    print(info_text(rec))
    topics = {t["topic"]: t for t in rec["topics"]}
    st = topics["/robot/state"]
    # one state per FRI cycle: 1 kHz over the simulated duration, none missing
    assert st["nominal_hz"] == 1000 and st["rate_hz"] == pytest.approx(1000, rel=1e-3)
    assert st["gaps"]["missing"] == 0 and st["gaps"]["gaps"] == 0 and st["gaps"]["largest_gap_s"] == 0.001
    est = topics["/estimator/phase"]
    assert est["nominal_hz"] == 100 and 50 < est["rate_hz"] <= 100.1 and est["gaps"]["missing"] == 0
    assert rec["result"]["reason"] == report["reproductions"][0]["reason"]
    assert rec["result"]["success"] == report["reproductions"][0]["success"]
    assert rec["result"]["sim_seconds"] == report["reproductions"][0]["sim_seconds"]
    assert rec["run_id"] == "infodiff-a" and rec["scenario"]["seed"] == 0
    assert rec["episode"] == {"kind": "reproduction", "index": 0}


@pytest.mark.slow
def test_diff_of_smoke_runs_same_seed_same_other_seed_differs(runs):
    same = diff_runs(runs["a"], runs["b"])
    print(same.text())
    assert same.same, same.first_difference
    assert {r.name for r in same.rows if r.a != r.b} >= {"run_id"}
    other = diff_runs(runs["a"], runs["c"])
    print(other.text())
    assert not other.same and not other.content_same
    first = other.first_difference
    assert first.startswith("demonstration_00.mcap /") and " seq " in first
    assert any(r.name == "seed" and r.differs for r in other.rows)
    # the rule is recorded_content's, file by file
    content = recorded_content(runs["c"])
    for name, rows in content.items():
        assert recording_content(runs["c"] / "recordings" / name).rows() == rows
