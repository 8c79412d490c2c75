"""A model made by ``etar learn`` from a run's recordings is a learned task a scenario
can reproduce (``model:``), the same as the runner's own learn stage makes."""

import pytest
import json

from services.cli.etar import main as etar
from services.scenario import Scenario
from tests import support

# whole runs in one process (seconds each): the slow lane
pytestmark = [pytest.mark.slow]


def test_a_model_learned_by_etar_learn_is_reproduced_by_a_scenario(tmp_path):
    demo = tmp_path / "demo"
    smoke = support.scenario("smoke").described()
    # the smoke scenario's demonstrations alone
    only_demos = Scenario.from_dict(dict(smoke, stages=[s for s in smoke["stages"] if "demonstrate" in s]))
    report = support.run(only_demos, demo, transport="inproc")
    assert report["error"] is None and len(report["demonstrations"]) == 2

    recordings = sorted(str(p) for p in (demo / "recordings").glob("demonstration_*.mcap"))
    assert etar(["learn", *recordings, "--phases", "3", "--restarts", "2", "--max-iter", "60",
                 "--out", str(tmp_path / "learned" / "model.json")]) == 0
    meta = json.loads((tmp_path / "learned" / "model.json").read_text())["metadata"]
    assert len(meta["goal"]) == 3 and len(meta["impedance"]) == 3
    assert sorted(meta["phase_to_truth"].values()) == [0, 1, 2]  # matched on the recordings' true labels

    reproduce = Scenario.from_dict(dict(name="reproduce_learned", world="valley", seed=0,
                                        model=str(tmp_path / "learned" / "model.json"),
                                        stages=[s for s in smoke["stages"] if "reproduce" in s]))
    report = support.run(reproduce, tmp_path / "repro", transport="inproc")
    assert report["error"] is None, report["error"]
    (rp,) = report["reproductions"]
    assert rp["success"], rp["reason"]
    assert rp["phases"]["accuracy"] > 0.8
