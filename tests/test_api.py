"""The Python API: docs/api.md's example runs as written, and a run made through the API
records exactly what the same scenario records through the command line."""

import re
import sys

import pytest

from services.cli import bench as bench_cli

pytestmark = [pytest.mark.slow]  # whole (small) runs in one process

ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    """docs/api.md's Python block, run from a folder laid out as the repository's root."""
    here = tmp_path_factory.mktemp("api")
    (here / "scenarios").symlink_to(ROOT / "scenarios")
    code = re.search(r"```python\n(.*?)```", (ROOT / "docs" / "api.md").read_text(), re.S).group(1)
    printed = []
    namespace = {"print": lambda *a, **k: printed.append(" ".join(str(x) for x in a))}
    mp = pytest.MonkeyPatch()
    mp.chdir(here)
    try:
        exec(compile(code, "docs/api.md", "exec"), namespace)
    finally:
        mp.undo()
    return here, namespace, printed


def test_the_documented_example_runs_and_its_accuracy_is_the_reports(example):
    here, ns, printed = example
    report = ns["record"].report
    assert report["error"] is None and (here / "runs" / "api-example" / "report.json").is_file()
    assert printed[0].startswith("3 phases; 1 of 1 reached the goal")
    accuracy = float(printed[1].split()[3])
    assert accuracy == pytest.approx(report["summary"]["online_phase_accuracy"], abs=5e-5)
    assert "run_scenario('scenarios/smoke.yaml'" in report["provenance"]["command"]


def test_a_run_through_the_api_records_what_the_command_line_records(example, capsys, monkeypatch):
    here, ns, _ = example
    monkeypatch.chdir(here)
    api_run = here / "runs" / "api-example"
    # the same scenario (seed 3) from the command line: the file the API run kept
    assert bench_cli.main(["run", str(api_run / "scenario.yaml"), "--transport", "inproc", "--no-figures",
                           "--out", "runs/cli-same"]) == 0
    assert bench_cli.main(["run", "scenarios/smoke.yaml", "--transport", "inproc", "--no-figures",
                           "--out", "runs/cli-seed0"]) == 0
    capsys.readouterr()
    assert bench_cli.main(["diff", str(api_run), "runs/cli-same"]) == 0
    same = capsys.readouterr().out
    assert "SAME: 3 recording(s)" in same
    assert bench_cli.main(["diff", str(api_run), "runs/cli-seed0"]) == 1
    differs = capsys.readouterr().out
    first = re.search(r"first difference: (\S+\.mcap) (/\S+) seq (\d+)", differs)
    assert first and first.group(1) == "demonstration_00.mcap", differs[:500]


def test_the_api_refuses_an_unknown_option_before_anything_starts(tmp_path):
    from services import run_scenario

    with pytest.raises(TypeError, match="unknown option"):
        run_scenario("scenarios/smoke.yaml", out=tmp_path / "x", transprot="inproc")
    assert not (tmp_path / "x").exists()


def test_the_api_names_its_own_arguments_and_takes_a_scenario_as_a_dict(tmp_path):
    """The API's errors name keyword arguments, not the command line's flags; a scenario
    may be a dict (validated as a file's would be), anything else is refused by its type."""
    from services import run_scenario
    from services.scenario import ScenarioError

    with pytest.raises(ValueError, match=r"^run_scenario: ready_timeout must be a number of seconds > 0") as err:
        run_scenario("scenarios/smoke.yaml", out=tmp_path / "x", ready_timeout=-5)
    assert "--" not in str(err.value)
    with pytest.raises(ValueError, match=r"^run_scenario: foxglove must be in 0\.\.65535"):
        run_scenario("scenarios/smoke.yaml", out=tmp_path / "x", foxglove=70000)
    with pytest.raises(ScenarioError, match=r"<run_scenario's dict>: name: use 1-55 letters"):
        run_scenario({"name": "my smoke", "world": "valley", "stages": [{"demonstrate": {"count": 1}}]},
                     out=tmp_path / "x")
    with pytest.raises(TypeError, match="scenario must be a Scenario, a dict or a YAML file's path, got int"):
        run_scenario(3, out=tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_importing_services_loads_no_runner():
    import subprocess

    done = subprocess.run([sys.executable, "-c", "import services, sys; "
                           "print('services.run.runner' in sys.modules, 'services.run.api' in sys.modules)"],
                          capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert done.stdout.split() == ["False", "False"], done
