"""End to end: the real service processes over Zenoh on loopback, driven by the runner."""

import json
import threading
import time
from collections import Counter
from pathlib import Path


from services.recording import read_episode
from services.runner import RunOptions, run

ROOT = Path(__file__).resolve().parents[2]
SMOKE = str(ROOT / "scenarios" / "smoke.yaml")
WALL_CLOCK_TOPICS = {"/robot/episode", "/runner/event"}  # wall-clock durations and loop timing


def content(run_dir: Path) -> dict:
    """Per recording file: the messages as (topic, payload without sent_ns), in seq order."""
    out = {}
    for path in sorted((run_dir / "recordings").glob("*.mcap")):
        msgs = []
        for m in read_episode(path).messages:
            if m.topic in WALL_CLOCK_TOPICS:
                continue
            d = json.loads(m.payload)
            d.pop("sent_ns", None)
            msgs.append((m.topic, d["seq"], json.dumps(d, sort_keys=True)))
        out[path.name] = sorted(msgs)
    return out


def check_recordings(run_dir: Path, report: dict) -> None:
    for d in report["demonstrations"] + report["reproductions"]:
        ep = read_episode(d["path"])
        assert ep.complete
        # every (topic, seq) once: nothing from another run, nothing twice
        counts = Counter((m.topic, json.loads(m.payload)["seq"]) for m in ep.messages
                         if m.topic not in WALL_CLOCK_TOPICS)
        assert max(counts.values()) == 1
        topics = set(ep.topics())
        assert {"/robot/state", "/robot/contact", "/ft/wrench"} <= topics
        # a JSON Schema on every channel: Foxglove plots the wrench and phase topics from it
        for ch in ep.channels.values():
            assert ch.schema_encoding == "jsonschema" and json.loads(ch.schema_data)["type"] == "object"
        assert "wrench" in json.loads(ep.channels["/ft/wrench"].schema_data)["properties"]


def test_smoke_lockstep_twice_at_once_is_deterministic_and_isolated(tmp_path):
    """Two runs of the same seed at the same time, under different run ids: both
    complete, neither sees the other's messages, and they recorded the same thing."""
    results = {}

    def go(name):
        t = time.monotonic()
        results[name] = (run(RunOptions(scenario=SMOKE, out=str(tmp_path / name), run_id=f"e2e-{name}-{int(t)}"),
                             progress=lambda m: print(f"[{name}] {m}")), time.monotonic() - t)

    threads = [threading.Thread(target=go, args=(n,)) for n in ("a", "b")]
    for th in threads:
        th.start()
    for th in threads:
        th.join(600)
    for name in ("a", "b"):
        report, seconds = results[name]
        print(f"run {name}: {seconds:.1f} s wall")
        assert report["error"] is None, report["error"]
        assert len(report["demonstrations"]) == 2 and len(report["reproductions"]) == 1
        assert report["summary"]["phases_chosen"] == 3
        assert all(code == 0 for code in report["exit_codes"].values()), report["exit_codes"]
        check_recordings(tmp_path / name, report)
        assert (tmp_path / name / "report.txt").read_text().startswith("ETAR testbench run")
        assert (tmp_path / name / "model.json").exists()
    a, b = content(tmp_path / "a"), content(tmp_path / "b")
    assert a.keys() == b.keys() and len(a) == 3
    for name in a:
        assert a[name] == b[name], f"{name} differs between two runs of the same seed"


def test_smoke_realtime_completes_with_its_deadline_report(tmp_path):
    t = time.monotonic()
    report = run(RunOptions(scenario=SMOKE, out=str(tmp_path), clock="realtime"), progress=print)
    print(f"realtime smoke: {time.monotonic() - t:.1f} s wall")
    assert report["error"] is None, report["error"]
    assert report["environment"]["clock"] == "realtime"
    loop = report["timing"]["robot_loop"]
    assert loop["cycles"] > 5000
    assert loop["deadline_misses"] >= 0 and "longest_miss_run" in loop
    per = loop["per_episode"][0]
    assert per["lateness"]["p50_us"] >= 0 and per["execution"]["max_us"] > 0
    # realtime: the simulated time tracks the wall clock
    s = report["summary"]
    assert 0.5 < s["real_time_factor"] < 1.2
    assert "deadline misses" in (tmp_path / "report.txt").read_text()
