"""A model made by ``etar learn`` from a run's recordings is a learned task a scenario
can reproduce (``model:``), the same as the runner's own learn stage makes."""

import json
from pathlib import Path

from services.cli.etar import main as etar
from services.run.runner import RunOptions, run

ROOT = Path(__file__).resolve().parents[2]


def test_a_model_learned_by_etar_learn_is_reproduced_by_a_scenario(tmp_path):
    demo = tmp_path / "demo"
    smoke = (ROOT / "scenarios" / "smoke.yaml").read_text()
    # the smoke scenario's demonstrations alone
    only_demos = smoke[:smoke.index("  - learn:")]
    (tmp_path / "demos.yaml").write_text(only_demos)
    report = run(RunOptions(figures=False, scenario=str(tmp_path / "demos.yaml"), out=str(demo), transport="inproc"))
    assert report["error"] is None and len(report["demonstrations"]) == 2

    recordings = sorted(str(p) for p in (demo / "recordings").glob("demonstration_*.mcap"))
    assert etar(["learn", *recordings, "--phases", "3", "--restarts", "2", "--max-iter", "60",
                 "--out", str(tmp_path / "learned" / "model.json")]) == 0
    meta = json.loads((tmp_path / "learned" / "model.json").read_text())["metadata"]
    assert len(meta["goal"]) == 3 and len(meta["impedance"]) == 3
    assert sorted(meta["phase_to_truth"].values()) == [0, 1, 2]  # matched on the recordings' true labels

    reproduce = smoke[smoke.index("  - reproduce:"):]
    (tmp_path / "reproduce.yaml").write_text(
        "name: reproduce_learned\nworld: valley\nseed: 0\nmodel: learned/model.json\nstages:\n" + reproduce)
    report = run(RunOptions(figures=False, scenario=str(tmp_path / "reproduce.yaml"), out=str(tmp_path / "repro"),
                            transport="inproc"))
    assert report["error"] is None, report["error"]
    (rp,) = report["reproductions"]
    assert rp["success"], rp["reason"]
    assert rp["phases"]["accuracy"] > 0.8
