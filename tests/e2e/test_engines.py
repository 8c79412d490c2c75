"""The two in-process engines, per-message (services.transport.inproc) and fused
(services.transport.fused): the same seed records the same messages, message for message
(payloads without sent_ns, as ``etar-bench diff`` compares them), and gives the same
results, faults included."""

import pytest

from services.nodes.ft_sensor import FtSensorNode
from services.results.diff import diff_runs
from tests import support
from tests.support import run

SUMMARY = ("phases_chosen", "successes", "online_phase_accuracy", "mean_transition_error_s", "simulated_seconds")


def both(scenario, tmp_path, **options) -> tuple[dict, dict]:
    """``scenario`` run once per engine; their reports."""
    reports = {}
    for engine in ("per-message", "fused"):
        reports[engine] = run(scenario, tmp_path / engine, progress=lambda m, e=engine: print(f"[{engine}] {m}"),
                              transport="inproc", engine=engine, run_id=f"engines-{engine}", **options)
        assert reports[engine]["error"] is None, (engine, reports[engine]["error"])
    return reports["per-message"], reports["fused"]


def assert_same(tmp_path, a: dict, b: dict) -> None:
    d = diff_runs(tmp_path / "per-message", tmp_path / "fused")
    assert d.same, d.first_difference
    assert d.files and all(f.messages_a > 1000 for f in d.files), [(f.name, f.messages_a) for f in d.files]
    for key in SUMMARY:
        assert a["summary"][key] == b["summary"][key], key
    episodes = [[{k: v for k, v in e.items() if k != "wall_seconds"} for e in r["demonstrations"] + r["reproductions"]]
                for r in (a, b)]
    assert episodes[0] == episodes[1]  # why each ended, its FRI link, peak force, final position, phases


def test_the_smoke_records_the_same_messages_with_either_engine(tmp_path, monkeypatch):
    # every message the fused engine hands over in memory is checked against what its bytes decode to
    monkeypatch.setenv("ETAR_INPROC_CHECK", "1")
    a, b = both(support.scenario("smoke"), tmp_path)
    assert_same(tmp_path, a, b)
    assert b["summary"]["successes"] == 1 and b["transport"] == "inproc"


def test_a_node_whose_work_raises_is_counted_and_the_run_goes_on_alike(tmp_path, monkeypatch):
    """The sensor fails on every 50th contact message of a demonstration: each engine counts
    it as a bad message of the sensor, the robot closes that cycle without the sensor's
    answer, and both record the same messages."""
    real = FtSensorNode.sample

    def failing(self, msg, message=True):
        if msg["episode"] >= 0 and msg["seq"] % 50 == 0:
            raise ValueError(f"injected: cycle {msg['seq']}")
        return real(self, msg, message)

    monkeypatch.setattr(FtSensorNode, "sample", failing)
    demonstration = support.scenario("smoke").described()
    demonstration["stages"] = [{"demonstrate": dict(demonstration["stages"][0]["demonstrate"], count=1)}]
    from services.scenario import Scenario

    a, b = both(Scenario.from_dict(demonstration), tmp_path)
    assert_same(tmp_path, a, b)
    bad = [r["timing"]["links_received"]["robot/contact -> ft_sensor"] for r in (a, b)]
    assert bad[0] == bad[1] and bad[0]["bad"] > 10 and "injected" in bad[0]["last_error"]
    assert a["demonstrations"][0]["reason"] == "teacher_done"


# each cut to what it has that the smoke has not, learning kept short (how a model is
# learned is not the engines' business); the whole scenarios are compared by `etar-bench diff`
# (docs/engine.md)
SHORT_LEARN = {"learn.phases": 2, "learn.restarts": 1, "learn.max_iter": 30}


@pytest.mark.slow
@pytest.mark.parametrize("name, changes", [
    # the FRI link's faults: command packets lost for 60 ms at 7 s, command mode left and entered
    # again at 7.86 s; the reproduction cut at 8.5 s
    ("fri_dropout", {"reproduce.count": 1, "reproduce.max_seconds": 8.5}),
    # the coupler's world, pose state and force/torque features, the turn at the goal (the
    # valley's world is the smoke's, above)
    ("hose_coupler", {"demonstrate.count": 1, "reproduce.count": 1, "reproduce.max_seconds": 10, **SHORT_LEARN}),
])
def test_each_scenario_records_the_same_messages_with_either_engine(tmp_path, name, changes):
    a, b = both(support.scenario(name, changes), tmp_path)
    assert_same(tmp_path, a, b)
    if name == "fri_dropout":  # the dropout happened: command mode left, and entered again
        assert [(b["reproductions"][0]["fri"][k]) for k in ("command_mode_left", "command_mode_entered")] == [1, 2]
