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
from services.run.sweep import Parameter, SweepError, plan, sweep
from services.scenario import Scenario, load_scenario
from tests import support

ROOT = Path(__file__).resolve().parents[2]


def reproduction_scenario() -> Scenario:
    """The smoke scenario's reproduction with its stored model: no demonstrations, no learning."""
    return Scenario.from_dict(dict(name="repro", world="valley", seed=0, model=support.SMOKE_MODEL, stages=[
        {"reproduce": dict(count=1, start=[0.62, -0.06, 0.30], start_perturbation=0.01, goal_x=0.57,
                           max_seconds=15)}]))


def test_parameters_are_parsed_and_every_combination_validated_before_anything_runs(tmp_path):
    p = Parameter.parse("reproduce.start_perturbation=0.005,1e-2")
    assert p.values == (0.005, 0.01)
    assert Parameter.parse("demonstrate.sides=[left],[left,right]").values == (["left"], ["left", "right"])
    with pytest.raises(SweepError, match="expected PATH=V1,V2"):
        Parameter.parse("reproduce.count")
    scenario = reproduction_scenario()
    with pytest.raises(SweepError, match=r"cell.sensor_noise: expected a finite number >= 0, got -1"):
        plan(scenario, [Parameter.parse("cell.sensor_noise=1,-1")], 1, tmp_path / "out", "none", 1)
    # a refused sweep leaves nothing of a sweep behind, so the corrected command is not refused
    with pytest.raises(SweepError, match=r"cell.sensor_noise: expected a finite number >= 0, got -1"):
        sweep(scenario, [Parameter.parse("cell.sensor_noise=1,-1")], repeats=1, out=str(tmp_path / "refused"))
    assert not (tmp_path / "refused").exists()  # not even its folder: every value is checked first
    with pytest.raises(SweepError, match="no values"):
        Parameter.parse("cell.sensor_noise=,")
    with pytest.raises(SweepError, match="learn.phases: the scenario has no learn stage"):
        plan(scenario, [Parameter.parse("learn.phases=3")], 1, tmp_path / "out", "none", 1)
    specs = plan(scenario, [Parameter.parse("cell.sensor_noise=0.5,2")], 2, tmp_path / "out", "none", 1)
    assert [(s.params["cell.sensor_noise"], s.seed) for s in specs] == [(0.5, 0), (0.5, 1), (2, 0), (2, 1)]
    # each run is a scenario value: its seed reaches the stage that inherits it
    assert [(s.scenario.cell.sensor_noise, s.scenario.reproduce_stages[0].seed) for s in specs] == [
        (0.5, 2000), (0.5, 2001), (2.0, 2000), (2.0, 2001)]
    # and is written down as what ran, which reads back as the same scenario
    for s in specs:
        assert load_scenario(tmp_path / "out" / "scenarios" / f"{s.name}.yaml").to_dict() == s.scenario.to_dict()


def test_a_sweep_draws_the_visual_topics_only_into_recordings_it_keeps(tmp_path):
    from services.run.configs import node_configs
    from services.runtime.visual_topics import VISUAL_RATE_HZ

    for record, rate in (("full", VISUAL_RATE_HZ), ("summary", 0), ("none", 0)):
        spec, = plan(reproduction_scenario(), [], 1, tmp_path / record, record, 1)
        recorder = node_configs(spec.scenario, spec.options(), ["recorder"], tmp_path, True)["recorder"]
        assert recorder.visual_rate_hz == rate, record


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


@pytest.mark.slow
def test_a_sweep_on_local_processes(tmp_path):
    out = tmp_path / "sweep"
    t = time.monotonic()
    result = sweep(reproduction_scenario(), [Parameter.parse("reproduce.start_perturbation=0.005,0.01")],
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


@pytest.mark.slow
def test_a_sweep_on_a_dask_cluster(tmp_path, dask_cluster):
    out = tmp_path / "sweep"
    t = time.monotonic()
    result = sweep(reproduction_scenario(), [Parameter.parse("reproduce.start_perturbation=0.005,0.01")],
                   repeats=1, out=str(out), record="none", workers=2, cluster=dask_cluster, say=print)
    print(f"dask sweep: {time.monotonic() - t:.1f} s")
    assert result["cluster"] == dask_cluster
    check(result, out, 2, "none")
    worker_log = (tmp_path / "worker.log").read_text()
    assert re.search(r"Registered to", worker_log), worker_log[-2000:]


@pytest.mark.slow
@pytest.mark.serial  # a real SIGINT to the test's own process: not in an xdist worker
def test_a_sweep_on_a_dask_cluster_interrupted_cancels_what_it_had_not_finished_there(tmp_path, dask_cluster):
    """Ctrl-C to a sweep on a Dask cluster: the runs not finished are cancelled there, said in
    one line that a run already under way runs on to its end (Dask does not stop a running
    task), and sweep.json is marked incomplete with them as cancelled_on_cluster.  Before, the
    sweep said it was interrupted "before any run started" while its runs went on, and wrote
    no sweep.json."""
    import threading

    from services.run.sweep import SweepInterrupted

    out, said = tmp_path / "sweep", []

    def interrupt_once_a_run_records():
        support.wait_until(lambda: any((out / "runs").glob("run*/recordings/*.mcap")), 120, "a run records")
        os.kill(os.getpid(), signal.SIGINT)

    # this process's SIGINT as a terminal's: a shell that started the tests in the background without job
    # control left it ignored (every process under it inherits that), and the sweep would run to its end
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    threading.Thread(target=interrupt_once_a_run_records, daemon=True).start()
    try:
        with pytest.raises(SweepInterrupted) as stop:
            sweep(reproduction_scenario(), [Parameter.parse("reproduce.start_perturbation=0.005,0.01,0.015,0.02")],
                  repeats=1, out=str(out), record="summary", workers=2, cluster=dask_cluster, say=said.append)
    finally:
        signal.signal(signal.SIGINT, before)
    summary = json.loads((out / "sweep.json").read_text())
    assert summary == stop.value.summary and summary["incomplete"] == "interrupted (SIGINT)"
    cancelled = summary["cancelled_on_cluster"]
    assert cancelled and not set(cancelled) & set(summary["not_started"]), summary
    assert summary["runs"] + len(cancelled) + len(summary["not_started"]) == 4, summary
    assert any("cancelled on the cluster; one already under way there runs on" in line for line in said), said


@pytest.mark.slow
def test_a_sweep_of_etar_against_star_over_data_seeds(tmp_path):
    """The smoke scenario learning both transition models and reproducing its start with
    each, over two data seeds: a row per run and model, each run's own figures, and the
    verdict over the seeds."""
    scenario = support.scenario("smoke", {"learn.transitions": ["effect", "state"],
                                          "reproduce.transitions": ["effect", "state"]})
    out = tmp_path / "sweep"
    result = sweep(scenario, [], repeats=2, out=str(out), record="summary", workers=2, say=print)
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


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (the pool's workers and its resource tracker)."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry.name))
    return out


def _sweep_until_a_run_ends(tmp_path, values: str, popen=subprocess.Popen):
    """A local sweep of the stored model's reproduction over ``values`` of its start
    perturbation on two workers, started and read until its first run has finished: the
    process, the lines it said, its folder."""
    scenario_file = tmp_path / "repro.yaml"
    scenario_file.write_text(reproduction_scenario().to_yaml())
    out = tmp_path / "sweep"
    sweeper = popen(
        [sys.executable, "-m", "services.cli.bench", "sweep", str(scenario_file), "--param",
         f"reproduce.start_perturbation={values}", "--workers", "2", "--record", "summary",
         "--out", str(out)], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        start_new_session=True)
    said = []
    for line in sweeper.stderr:
        said.append(line)
        if re.search(rf"\[1/{len(values.split(','))}, ", line):
            break
    return sweeper, said, out


def _spawned_workers(pid: int) -> list[int]:
    """``pid``'s pool workers (multiprocessing's spawn_main), not its resource tracker."""
    found = []
    for p in _children(pid):
        try:
            if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes():
                found.append(p)
        except OSError:  # gone since it was listed
            pass
    return found


@pytest.mark.slow
def test_a_sweep_whose_worker_is_killed_runs_what_it_left_again_and_loses_nothing(tmp_path):
    """A worker killed mid-run (the OOM killer, a kill -9) breaks the whole pool: every run
    not finished fails with BrokenProcessPool, the other worker's too.  The sweep says so in
    one line and runs those again in a new pool, into their folders: all four rows, exit 0.
    Before, it ended in a BrokenProcessPool traceback with no table and no sweep.json."""
    sweeper, said, out = _sweep_until_a_run_ends(tmp_path, "0.005,0.01,0.015,0.02")
    try:
        workers = _spawned_workers(sweeper.pid)
        assert len(workers) == 2, (workers, "".join(said))
        os.kill(workers[0], signal.SIGKILL)
        code = sweeper.wait(timeout=120)
        said += sweeper.stderr.readlines()
    finally:
        if sweeper.poll() is None:
            os.killpg(sweeper.pid, signal.SIGKILL)
    text = "".join(said)
    assert code == 0 and "Traceback" not in text, (code, text)
    assert re.search(r"sweep: a worker process died \(BrokenProcessPool: .*\); the \d run\(s\) it left unfinished "
                     r"start again in a new pool", text), text
    rows = json.loads((out / "table.json").read_text())
    assert sorted(r["run"] for r in rows) == ["run000", "run001", "run002", "run003"]
    assert all(r["error"] is None for r in rows), rows
    assert json.loads((out / "sweep.json").read_text())["runs"] == 4


@pytest.mark.slow
@pytest.mark.serial
@pytest.mark.parametrize("how", ["SIGTERM to the sweep", "Ctrl-C to its group"])
def test_an_interrupted_sweep_keeps_what_finished_and_leaves_no_worker(tmp_path, how):
    """A local sweep of six runs on two workers, stopped once the first run has finished:
    the sweep exits 130 in one line, no worker outlives it, nothing starts after the signal,
    the finished runs are tabulated with sweep.json marked incomplete, and each run that was
    under way has its partial report."""
    sweeper, said, out = _sweep_until_a_run_ends(tmp_path, "0.005,0.01,0.015,0.02,0.025,0.03",
                                                  popen=support.popen_as_from_a_terminal)
    try:
        workers = _children(sweeper.pid)
        assert len(workers) >= 2, (workers, "".join(said))
        if how.startswith("SIGTERM"):
            sweeper.send_signal(signal.SIGTERM)
        else:
            os.killpg(sweeper.pid, signal.SIGINT)
        t0 = time.monotonic()
        code = sweeper.wait(timeout=90)
        took = time.monotonic() - t0
        said += sweeper.stderr.readlines()
    finally:
        if sweeper.poll() is None:
            os.killpg(sweeper.pid, signal.SIGKILL)
    text = "".join(said)
    assert code == 130 and took < 30, (code, took, text)
    assert "Traceback" not in text, text
    def alive():
        found = {}
        for p in workers:
            try:
                found[p] = Path(f"/proc/{p}/cmdline").read_bytes().replace(b"\0", b" ")[:120]
            except OSError:  # gone
                pass
        return found
    # the resource tracker ends once it reads the sweep's end
    support.wait_until(lambda: not alive(), 5.0, "no worker outlives the sweep", poll_s=0.1, seen=alive)
    last = text.strip().splitlines()[-1]
    assert last.startswith("etar-bench sweep: interrupted (") and "sweep.json marked incomplete" in last, last
    summary = json.loads((out / "sweep.json").read_text())
    assert summary["incomplete"].startswith("interrupted (")
    finished = [r["run"] for r in json.loads((out / "table.json").read_text())]
    assert len(finished) >= 1 and summary["runs"] == len(finished)
    assert len(finished) + len(summary["interrupted_runs"]) + len(summary["not_started"]) == 6, summary
    for run in finished + summary["interrupted_runs"]:
        assert (out / "runs" / run / "report.json").exists(), run
    for run in summary["interrupted_runs"]:
        assert json.loads((out / "runs" / run / "report.json").read_text())["error"].startswith("interrupted (")
    for run in summary["not_started"]:
        assert not (out / "runs" / run).exists(), f"{run} started after the signal"


def test_a_run_gives_back_the_signal_handlers_it_took(tmp_path):
    """A run takes SIGINT and SIGTERM while it writes its report (``Runner._escalate_on_next_interrupt``)
    and gives them back when it returns: a sweep's pool worker starts its next run with its own
    handlers.  Before, a worker's second run kept the first run's, so the sweep's Ctrl-C did not
    stop it and the worker then started a run the sweep listed as never started (CI, 2026-12-06)."""
    def mine(signum, frame):
        pass

    before = {s: signal.signal(s, mine) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        report = support.run(support.hold(0.3, {"clock": "lockstep"}), tmp_path / "run", transport="inproc",
                             run_id="handlers")
        assert report["error"] is None
        assert signal.getsignal(signal.SIGINT) is mine and signal.getsignal(signal.SIGTERM) is mine
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


@pytest.mark.slow
@pytest.mark.serial
def test_a_sweep_in_one_process_stops_at_the_first_ctrl_c(tmp_path):
    """``--workers 1``: the runs one after the other in the sweep's process.  Ctrl-C while the
    first runs: it writes its partial report and no other run starts; exit 130 in one line,
    sweep.json marked incomplete.  Before, the interrupted run was a failed row and the sweep
    went on with the next runs, exiting 1 once they were done."""
    scenario_file = tmp_path / "repro.yaml"
    scenario_file.write_text(reproduction_scenario().to_yaml())
    out = tmp_path / "sweep"
    sweeper = support.popen_as_from_a_terminal(
        [sys.executable, "-m", "services.cli.bench", "sweep", str(scenario_file), "--param",
         "reproduce.start_perturbation=0.005,0.01,0.015", "--workers", "1", "--record", "summary", "--out", str(out)],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        # the first run under way: its reproduction is being recorded
        support.wait_until(lambda: any((out / "runs" / "run000" / "recordings").glob("*.mcap")), 60,
                           "the first run records its reproduction")
        os.killpg(sweeper.pid, signal.SIGINT)
        code = sweeper.wait(timeout=60)
        said = sweeper.stderr.read()
    finally:
        if sweeper.poll() is None:
            os.killpg(sweeper.pid, signal.SIGKILL)
    last = said.strip().splitlines()[-1]
    assert code == 130 and "Traceback" not in said, said
    assert last.startswith("etar-bench sweep: interrupted (SIGINT)") and "2 not started" in last, last
    summary = json.loads((out / "sweep.json").read_text())
    assert summary["interrupted_runs"] == ["run000"] and summary["not_started"] == ["run001", "run002"], summary
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["run000"]
    assert json.loads((out / "runs" / "run000" / "report.json").read_text())["error"].startswith("interrupted (")
