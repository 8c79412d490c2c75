"""A run is reproducible from what it leaves: the report names the code, the date, the
command and the libraries; the folder keeps the scenario as run; one folder holds one
run, and nothing of an earlier run is ever shown as this one's."""

import json
import shutil
import subprocess

import pytest

from services.cli import bench as bench_cli
from services.scenario import load_scenario
from tests import support

pytestmark = [pytest.mark.slow]  # whole (small) runs in one process


def cli_run(out, *more, scenario="scenarios/smoke.yaml"):
    return bench_cli.main(["run", str(scenario), "--transport", "inproc", "--out", str(out), *more])


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """The smoke scenario run from the command line, without figures."""
    out = tmp_path_factory.mktemp("folder") / "plain"
    assert cli_run(out, "--no-figures", "--run-id", "plain") == 0
    return out


def test_the_report_names_the_code_the_date_the_command_and_the_libraries(plain):
    report = json.loads((plain / "report.json").read_text())
    p = report["provenance"]
    assert p["version"] and len(p["commit"]) == 40 and isinstance(p["dirty"], bool)
    assert p["date"].startswith("20") and p["date"].endswith("+00:00")
    assert "run scenarios/smoke.yaml --transport inproc" in p["command"] and "--no-figures" in p["command"]
    assert p["dependencies"]["numpy"] and p["dependencies"]["mujoco"] and p["dependencies"]["eclipse-zenoh"]
    assert report["transport"] == "inproc" and report["environment"]["clock"] == "lockstep"
    text = (plain / "report.txt").read_text()
    assert f"git {p['commit'][:7]}" in text and "transport inproc" in text and p["command"] in text


def test_the_folder_keeps_the_scenario_as_run(plain):
    kept = load_scenario(plain / "scenario.yaml")
    assert kept.to_dict() == support.scenario("smoke").to_dict()


def test_a_folder_that_holds_a_run_is_refused_unless_asked_to_replace_it(plain, capsys):
    before = (plain / "report.json").read_bytes()
    assert cli_run(plain, "--no-figures") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"etar-bench run: error: --out {plain}: {plain} already holds a run; choose another folder, or "
                   "--replace to remove that run first"]
    assert (plain / "report.json").read_bytes() == before  # nothing of it was touched


def test_lockstep_timing_is_reported_as_simulated_and_host_figures_are_labelled(plain):
    text = (plain / "report.txt").read_text()
    assert "timing (simulated):" in text and "deadline misses" not in text
    assert "host latency, publish -> recorder (us):" in text and "link latency" not in text
    assert not (plain / "timing.png").exists()  # its histograms would be the host's, drawn as the loop's
    assert json.loads((plain / "report.json").read_text())["timing"]["basis"] == "host wall clock (lockstep)"


def test_report_exits_1_for_a_failed_run_and_its_json_is_strict(plain, tmp_path, capsys):
    failed = tmp_path / "failed"
    shutil.copytree(plain, failed)
    report = json.loads((failed / "report.json").read_text())
    report["error"] = "RuntimeError: the recorder died"
    report["summary"]["mean_transition_error_s"] = float("nan")  # as reports written before could hold
    (failed / "report.json").write_text(json.dumps(report))
    assert bench_cli.main(["report", str(plain)]) == 0
    capsys.readouterr()
    assert bench_cli.main(["report", str(failed), "--json"]) == 1
    captured = capsys.readouterr()
    printed = json.loads(captured.out, parse_constant=lambda c: pytest.fail(f"{c} in report --json"))
    assert printed["summary"]["mean_transition_error_s"] is None
    assert captured.err.strip() == "etar-bench report: the run failed: RuntimeError: the recorder died"


def page_images(run_dir):
    """The figure names report.html embeds (its captions)."""
    import re

    return sorted(re.findall(r"<figcaption>([^<]+\.png)</figcaption>", (run_dir / "report.html").read_text()))


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def rendered_images(page, tmp_path) -> str:
    """``loaded/all`` images of ``page`` in a headless browser."""
    dom = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                          "--disable-background-networking", "--disable-component-update", "--disable-sync",
                          f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=5000", "--dump-dom",
                          page.as_uri()], capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0, dom.stderr[-2000:]
    import re

    found = re.search(r'data-images="(\d+/\d+)"', dom.stdout)
    assert found, dom.stdout[:500]
    return found.group(1)


def test_figures_rebuilds_every_figure_and_the_page_of_a_run_made_without_them(plain, tmp_path, capsys):
    run_dir = tmp_path / "rebuilt"
    shutil.copytree(plain, run_dir)
    assert not (run_dir / "report.html").exists() and not (run_dir / "figures").exists()
    assert bench_cli.main(["figures", str(run_dir)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("figures: ") and "report.html" in line
    drawn = sorted(p.name for p in (run_dir / "figures").glob("*.png"))
    assert len(drawn) >= 5 and page_images(run_dir) == drawn
    if CHROMIUM:
        assert rendered_images(run_dir / "report.html", tmp_path) == f"{len(drawn)}/{len(drawn)}"


def test_a_replaced_run_never_shows_a_figure_of_the_run_before(tmp_path, capsys):
    """The first run chooses its phase count by BIC (a BIC figure); the second, into the
    same folder, fixes it: no BIC figure may appear in its page, in the folder or in the
    browser."""
    out = tmp_path / "reused"
    first = support.scenario("smoke", {"learn.phases": "auto", "learn.candidates": [2, 3]})
    path = tmp_path / "bic.yaml"
    path.write_text(first.to_yaml())
    assert cli_run(out, scenario=path) == 0
    assert "bic_by_phase_count.png" in page_images(out)
    stale = out / "figures" / "reproduction_07_force_phase_alpha.png"  # as a longer earlier run would leave
    shutil.copy(out / "figures" / "bic_by_phase_count.png", stale)
    old_bag = out / "rosbag2" / "reproduction_00"  # as `etar-bench export --rosbag2` of it would leave
    old_bag.mkdir(parents=True)
    assert cli_run(out, "--replace") == 0
    capsys.readouterr()
    drawn = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert "bic_by_phase_count.png" not in drawn and not stale.exists() and not old_bag.parent.exists()
    assert page_images(out) == drawn
    assert json.loads((out / "report.json").read_text())["learning"]["selection"]["best"] == 3
    if CHROMIUM:
        assert rendered_images(out / "report.html", tmp_path) == f"{len(drawn)}/{len(drawn)}"
