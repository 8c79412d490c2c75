"""Sweeps: every combination x seed as an in-process run, on a local pool and on a real
Dask cluster (a scheduler and a worker started here as their own processes)."""

import csv
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.transport import launch
from services.run.sweep import Parameter, SweepError, apply, plan, sweep

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "scenarios" / "models" / "smoke.json"


def reproduction_scenario(tmp_path) -> Path:
    """The smoke scenario's reproduction with its stored model: no demonstrations, no learning."""
    path = tmp_path / "repro.yaml"
    path.write_text(f"""name: repro
world: valley
seed: 0
model: {MODEL}
stages:
  - reproduce:
      count: 1
      start: [0.62, -0.06, 0.30]
      start_perturbation: 0.01
      goal_x: 0.57
      max_seconds: 15
""")
    return path


def test_parameters_are_parsed_applied_and_validated_before_anything_runs(tmp_path):
    p = Parameter.parse("reproduce.start_perturbation=0.005,1e-2")
    assert p.values == (0.005, 0.01)
    assert Parameter.parse("demonstrate.sides=[left],[left,right]").values == (["left"], ["left", "right"])
    data = {"seed": 0, "stages": [{"demonstrate": {"count": 2}}, {"reproduce": {"count": 1}},
                                  {"reproduce": None}]}
    apply(data, "reproduce.count", 5)
    apply(data, "reproduce[1].goal_x", 0.5)
    apply(data, "cell.sensor_noise", 2.0)
    assert data["stages"][1]["reproduce"]["count"] == 5 and data["stages"][2]["reproduce"] == {"count": 5,
                                                                                                "goal_x": 0.5}
    assert data["cell"] == {"sensor_noise": 2.0}
    with pytest.raises(SweepError, match="expected PATH=V1,V2"):
        Parameter.parse("reproduce.count")
    with pytest.raises(SweepError, match="STAGE one of demonstrate, learn, reproduce"):
        apply(data, "teach.count", 1)
    with pytest.raises(SweepError, match="the scenario has no learn stage"):
        apply(data, "learn.phases", 3)
    scenario = reproduction_scenario(tmp_path)
    with pytest.raises(SweepError, match=r"cell.sensor_noise: expected a finite number >= 0, got -1"):
        plan(str(scenario), [Parameter.parse("cell.sensor_noise=1,-1")], 1, tmp_path / "out", "none", 1)
    specs = plan(str(scenario), [Parameter.parse("cell.sensor_noise=0.5,2")], 2, tmp_path / "out", "none", 1)
    assert [(s.params["cell.sensor_noise"], s.seed) for s in specs] == [(0.5, 0), (0.5, 1), (2, 0), (2, 1)]


def check(result, out: Path, n_runs: int, record: str):
    assert result["runs"] == n_runs and result["failed"] == 0, result
    rows = list(csv.DictReader((out / "table.csv").open()))
    assert len(rows) == n_runs
    for row in rows:
        assert row["error"] == "" and row["phases_chosen"] == "3"
        assert int(row["successes"]) == int(row["reproductions"]) == 1
        assert 0.5 < float(row["online_phase_accuracy"]) <= 1.0 and float(row["peak_contact_force_n"]) > 1.0
    assert json.loads((out / "table.json").read_text())[0]["run"] == "run000"
    assert (out / "reproduce_start_perturbation.png").stat().st_size > 10_000
    runs = sorted((out / "runs").iterdir()) if (out / "runs").exists() else []
    if record == "none":
        assert runs == []
    else:
        assert len(runs) == n_runs and all((r / "report.json").exists() for r in runs)
        assert all(not (r / "recordings").exists() for r in runs) == (record == "summary")


def test_a_sweep_on_local_processes(tmp_path):
    out = tmp_path / "sweep"
    t = time.monotonic()
    result = sweep(str(reproduction_scenario(tmp_path)), [Parameter.parse("reproduce.start_perturbation=0.005,0.01")],
                   repeats=1, out=str(out), record="summary", workers=2, say=print)
    print(f"local sweep: {time.monotonic() - t:.1f} s")
    check(result, out, 2, "summary")


@pytest.fixture
def dask_cluster(tmp_path):
    """A Dask scheduler and one worker process (two single-threaded workers), as a user starts them."""
    port = launch.free_port()
    address = f"tcp://127.0.0.1:{port}"
    dask = str(Path(sys.executable).with_name("dask"))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    logs = [open(tmp_path / "scheduler.log", "wb"), open(tmp_path / "worker.log", "wb")]
    scheduler = subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                                 stdout=logs[0], stderr=subprocess.STDOUT, env=env, start_new_session=True)
    worker = subprocess.Popen([dask, "worker", address, "--nworkers", "2", "--nthreads", "1", "--no-dashboard",
                               "--local-directory", str(tmp_path / "dask-worker")],
                              stdout=logs[1], stderr=subprocess.STDOUT, env=env, cwd=tmp_path, start_new_session=True)
    from distributed import Client

    try:
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)  # an event: the workers registered
        yield address
    finally:
        for p in (worker, scheduler):
            os.killpg(p.pid, signal.SIGKILL)  # nothing of theirs needs to outlive the test
        for p in (worker, scheduler):
            p.wait(30)
        for f in logs:
            f.close()


def test_a_sweep_on_a_dask_cluster(tmp_path, dask_cluster):
    out = tmp_path / "sweep"
    t = time.monotonic()
    result = sweep(str(reproduction_scenario(tmp_path)), [Parameter.parse("reproduce.start_perturbation=0.005,0.01")],
                   repeats=1, out=str(out), record="none", workers=2, cluster=dask_cluster, say=print)
    print(f"dask sweep: {time.monotonic() - t:.1f} s")
    assert result["cluster"] == dask_cluster
    check(result, out, 2, "none")
    worker_log = (tmp_path / "worker.log").read_text()
    assert re.search(r"Registered to", worker_log), worker_log[-2000:]


def test_a_sweep_of_etar_against_star_over_data_seeds(tmp_path):
    """The smoke scenario learning both transition models and reproducing its start with
    each, over two data seeds: a row per run and model, each run's own figures, and the
    verdict over the seeds."""
    text = (ROOT / "scenarios" / "smoke.yaml").read_text()
    text = text.replace("      max_iter: 60\n", "      max_iter: 60\n      transitions: [effect, state]\n")
    text += "      transitions: [effect, state]\n"  # the reproduce stage is the last
    assert text.count("transitions: [effect, state]") == 2
    scenario = tmp_path / "smoke_star.yaml"
    scenario.write_text(text)
    out = tmp_path / "sweep"
    result = sweep(str(scenario), [], repeats=2, out=str(out), record="summary", workers=2, say=print)
    assert result["runs"] == 2 and result["failed"] == 0, result
    rows = list(csv.DictReader((out / "table.csv").open()))
    assert [(r["seed"], r["param model"]) for r in rows] == [("0", "ETAR"), ("0", "STAR"), ("1", "ETAR"), ("1", "STAR")]
    for row in rows:
        assert float(row["success_rate"]) == 1.0 and 0.5 < float(row["online_phase_accuracy"]) <= 1.0
        assert 0.5 < float(row["filter_accuracy"]) <= 1.0 and float(row["filter_spurious_switches"]) >= 0
    comparison = (out / "comparison.txt").read_text()
    assert comparison.startswith("ETAR against STAR over 2 data seed(s) (0, 1)") and "the thesis' claim" in comparison
    assert (out / "model.png").stat().st_size > 10_000
    for run in sorted((out / "runs").iterdir()):
        report = json.loads((run / "report.json").read_text())
        assert sorted(report["learning"]["models"]) == ["ETAR", "STAR"]
        assert (run / report["learning"]["models"]["STAR"]["path"]).exists()
        assert [o["model"] for o in report["learning"]["offline"]] == ["ETAR", "STAR"]
        assert [r["model"] for r in report["reproductions"]] == ["ETAR", "STAR"]
        # the same start, each judged by its own model's phase mapping
        assert report["reproductions"][0]["start"] == report["reproductions"][1]["start"]
        assert all(r["phases"]["accuracy"] > 0.5 for r in report["reproductions"])
        assert "ETAR against STAR (thesis 6.3)" in (run / "report.txt").read_text()
