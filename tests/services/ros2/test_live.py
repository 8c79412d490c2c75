"""A lockstep run with ``--ros2`` (four short reproductions of the smoke task with its
stored model), watched by an rmw_zenoh client nobody here wrote
(zenoh-ros2-sdk, in its own process, a client of the run's Zenoh session as rmw_zenoh is
advised to join from outside): every /ft_sensor/wrench and /joint_states message of the
episodes it watched arrives with the recording's values, its graph query lists the cell's
topics with their types, a liveliness query finds the node and a publisher per topic, and a
late transient-local subscriber gets /robot_description.  Without ``--ros2`` nothing of
the cell is on ROS 2's wire."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from services.recordings.reader import read_episode
from services.ros2.types import TOPICS
from services.runtime.messages import FT_WRENCH, ROBOT_STATE
from tests.support import hold, popen_as_from_a_terminal

# a whole run over Zenoh and a second process watching it
pytestmark = [pytest.mark.slow, pytest.mark.zenoh]

ROOT = Path(__file__).resolve().parents[3]
ENDPOINT = re.compile(r"ROS 2: the cell is node /etar_cell in domain (\d+), on the Zenoh session at tcp/127\.0\.0\.1:(\d+)")


def test_an_rmw_zenoh_client_receives_every_message_with_the_recordings_values(tmp_path):
    out = tmp_path / "run"
    scenario = tmp_path / "reproductions.yaml"
    scenario.write_text(hold(2, {"clock": "lockstep", "reproduce.count": 4}).to_yaml())
    runner = popen_as_from_a_terminal(
        [sys.executable, "-m", "services.cli.bench", "run", str(scenario), "--ros2", "7",
         "--out", str(out), "--no-figures"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    said, judge = [], None
    try:
        for line in runner.stderr:
            said.append(line)
            found = ENDPOINT.search(line)
            if found:
                break
        assert found, "".join(said)
        domain, port = int(found.group(1)), int(found.group(2))
        assert domain == 7
        judge = subprocess.Popen([sys.executable, "-m", "tests.services.ros2.sdk_judge", str(port), str(domain),
                                  str(tmp_path / "judged.json")], cwd=ROOT, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        assert judge.stdout.readline().strip() == "subscribed", judge.stderr.read()
        rest = threading.Thread(target=lambda: said.extend(runner.stderr), daemon=True)
        rest.start()
        assert runner.wait(timeout=600) == 0, "".join(said)
        rest.join(10)
        judge.send_signal(signal.SIGTERM)
        assert judge.wait(timeout=60) == 0, judge.stderr.read()
    finally:
        for proc in (runner, judge):
            if proc is not None and proc.poll() is None:
                proc.kill()
    judged = json.loads((tmp_path / "judged.json").read_text())
    wrenches = {w[0]: w for w in judged["wrench"]}
    joints = {j[0]: j for j in judged["joint_states"]}
    assert wrenches and joints, judged
    # the episodes that began after the client subscribed: every message, the recording's values
    watched = 0
    for path in sorted((out / "recordings").glob("*.mcap")):
        messages = read_episode(path).messages
        recorded = [FT_WRENCH.decode(m.payload) for m in messages if m.topic == FT_WRENCH.channel]
        if recorded[0]["stamp_ns"] < min(wrenches):
            continue  # it began before the client was there
        watched += 1
        for w in recorded:
            assert w["stamp_ns"] in wrenches, f"{path.name}: wrench of {w['stamp_ns']} ns not received"
            assert wrenches[w["stamp_ns"]][1:] == ["ati_sensor", w["wrench"]]
        states = [ROBOT_STATE.decode(m.payload) for m in messages if m.topic == ROBOT_STATE.channel]
        for s in states:
            if s["seq"] % 10 == 0:
                assert s["stamp_ns"] in joints, f"{path.name}: joint state of {s['stamp_ns']} ns not received"
                assert joints[s["stamp_ns"]][2] == s["msr_jnt_pos"]
    print(f"the client watched {watched} whole episodes")
    assert watched >= 2, "the client watched fewer than two whole episodes"
    # the graph: topics with their types (the SDK's query), the node and its publishers (liveliness)
    assert dict((name, kinds) for name, kinds in judged["topics"]) == {t.name: [t.type] for t in TOPICS}
    tokens = judged["tokens"]
    assert [t for t in tokens if t.endswith("/NN/%/%/etar_cell")], tokens
    published = [t for t in tokens if "/MP/%/%/etar_cell/" in t]
    assert len(published) == len(TOPICS), published
    assert judged["robot_description"] and "<robot" in judged["robot_description"]
