"""The thesis' figures and the HTML report, from a small run in one process (the smoke
scenario with the phase count chosen by BIC, so that every figure has its data)."""

import base64
import shutil
import subprocess
from pathlib import Path

import pytest

from services.cli import bench as bench_cli
from services.results.figures import write_figures
from tests import support

# whole runs in one process (seconds each): the slow lane
pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[3]
FIGURES = ["demonstrations_position_and_force.png", "bic_by_phase_count.png", "forward_variable_demonstrations.png",
           "tool_path_by_phase.png", "prediction_error_by_step.png", "prediction_error_by_phase.png",
           "reproduction_00_force_phase_alpha.png"]
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def drawn_run(tmp_path_factory):
    """The run's folder, the recordings the results read while the report, the figures and
    the page were made (by file name, once per read), and the page as the run wrote it."""
    from services.results import decoding
    from services.results.figures import phases

    out = tmp_path_factory.mktemp("figures")
    scenario = support.scenario("smoke", {"learn.phases": "auto", "learn.candidates": [2, 3]})
    reads = []
    read = decoding.read_episode

    def counted(path):
        reads.append(Path(path).name)
        return read(path)

    def refused(path):
        raise AssertionError(f"the figures read {path} again")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(decoding, "read_episode", counted)
        patch.setattr(phases, "read_episode", refused)
        # workers 1: everything decoded in this process, where the reads are counted (with more,
        # the report's decoding goes on beside the run: tests/services/run/test_parallel_work.py)
        report = support.run(scenario, out / "run", figures=True, transport="inproc", run_id="figures", workers=1)
    assert report["error"] is None, report["error"]
    return out / "run", reads, (out / "run" / "report.html").read_text()


@pytest.fixture(scope="module")
def run_dir(drawn_run):
    return drawn_run[0]


def test_a_run_decodes_each_recording_once_for_its_report_and_figures(drawn_run):
    run_dir, reads, _ = drawn_run
    recordings = sorted(p.name for p in (run_dir / "recordings").glob("*.mcap"))
    assert sorted(reads) == recordings, reads
    assert not (run_dir / "figures.error").exists() and (run_dir / "report.html").is_file()


def test_every_run_writes_every_figure_as_a_png(run_dir):
    written = sorted(p.name for p in (run_dir / "figures").glob("*.png"))
    assert written == sorted(FIGURES), written
    for name in FIGURES:
        data = (run_dir / "figures" / name).read_bytes()
        width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
        assert data.startswith(PNG) and width >= 600 and height >= 300, (name, width, height)
    assert not (run_dir / "figures.error").exists()


def test_the_figures_command_draws_them_again_and_refuses_a_folder_that_is_no_run(run_dir, tmp_path, capsys):
    for p in (run_dir / "figures").glob("*.png"):
        p.unlink()
    assert bench_cli.main(["figures", str(run_dir)]) == 0
    printed = capsys.readouterr().out.strip()
    assert printed.startswith(f"figures: {len(FIGURES)} in {run_dir / 'figures'}, report.html"), printed
    assert sorted(p.name for p in (run_dir / "figures").glob("*.png")) == sorted(FIGURES)
    assert bench_cli.main(["figures", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"etar-bench figures: error: {tmp_path / 'report.json'}: missing (is {tmp_path} a " \
                      "finished run's folder?)"


def test_the_figures_command_fails_on_damaged_recordings_and_says_which(run_dir, tmp_path, capsys):
    """A recording the report names that is gone, or cut short: the figures are drawn from what
    can be read, figures.error names each damaged file, and the command exits 1 saying so; a
    report whose episodes are not a list is refused in one line, exit 2."""
    import json

    damaged = tmp_path / "damaged"
    shutil.copytree(run_dir, damaged)
    demos = sorted((damaged / "recordings").glob("demonstration_*.mcap"))
    assert len(demos) >= 2, demos
    demos[0].unlink()
    data = demos[1].read_bytes()
    demos[1].write_bytes(data[:len(data) // 2])
    capsys.readouterr()
    assert bench_cli.main(["figures", str(damaged)]) == 1
    err = capsys.readouterr().err
    assert f"damaged recording {demos[0]}" in err and f"damaged recording {demos[1]}" in err, err
    assert (damaged / "figures" / "demonstrations_position_and_force.png").is_file()  # from the cut one
    # a reproduction whose first part was cut where a restarted recorder's next part goes on: by
    # design, not damage; and a run that kept no recordings (a sweep's --record summary)
    parts = tmp_path / "parts"
    shutil.copytree(run_dir, parts)
    first = parts / "recordings" / "reproduction_00.mcap"
    whole = first.read_bytes()
    (parts / "recordings" / "reproduction_00.part2.mcap").write_bytes(whole)
    first.write_bytes(whole[:len(whole) * 3 // 10])
    report = json.loads((parts / "report.json").read_text())
    report["reproductions"][0]["recording_parts"] = ["recordings/reproduction_00.part2.mcap"]
    (parts / "report.json").write_text(json.dumps(report))
    shutil.rmtree(parts / "figures")
    assert bench_cli.main(["figures", str(parts)]) == 0, capsys.readouterr().err
    assert not (parts / "figures.error").exists()
    shutil.rmtree(parts / "recordings")
    assert bench_cli.main(["figures", str(parts)]) == 0, capsys.readouterr().err
    assert "kept no recordings" in (parts / "figures.skipped").read_text()
    report = json.loads((damaged / "report.json").read_text())
    report["demonstrations"] = "oops"
    (damaged / "report.json").write_text(json.dumps(report))
    assert bench_cli.main(["figures", str(damaged)]) == 2
    assert capsys.readouterr().err.strip().endswith("report.json: demonstrations: expected a list of episodes, got str")
    report["demonstrations"] = [{"index": 0}]
    (damaged / "report.json").write_text(json.dumps(report))
    assert bench_cli.main(["figures", str(damaged)]) == 2
    assert capsys.readouterr().err.strip().endswith(
        "report.json: demonstrations: expected each episode with its recording's path")

def test_a_run_without_demonstrations_says_which_figures_it_skips(tmp_path):
    report = support.run(support.scenario("fri_dropout", {"reproduce.count": 1}), tmp_path / "run", figures=True, transport="inproc",
                         run_id="nodemos")
    assert report["error"] is None
    written, skipped, damaged = write_figures(tmp_path / "run")
    # the stored valley model keeps the BIC scores its learn stage chose by
    assert [p.name for p in written] == ["bic_by_phase_count.png", "reproduction_00_force_phase_alpha.png"]
    assert any("no demonstrations" in s for s in skipped) and not any("no selection scores" in s for s in skipped)
    from services.results.figures.learning import bic_figure
    assert bic_figure({"criterion": "fixed"}, tmp_path) == "no selection scores (phase count fixed)"


def test_the_runs_figures_draw_its_world_and_name_its_phases_by_the_true_ones(run_dir, monkeypatch):
    """The world from the run's scenario.yaml, the phase mapping from its model, the
    reproduction scored as the report scores it."""
    import json

    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from robot_sim.world.labels import LABELERS
    from services.results.figures import canvas, phases

    kept = {}
    save = canvas.save
    monkeypatch.setattr(canvas, "save", lambda fig, path, *a, **k: kept.setdefault(Path(path).name, fig)
                        and save(fig, path, *a, **k))
    written, _, _ = write_figures(run_dir)
    assert sorted(p.name for p in written) == sorted(FIGURES)
    meta = json.loads((run_dir / "model.json").read_text())["metadata"]
    k = json.loads((run_dir / "model.json").read_text())["n_phases"]
    names = phases.phase_labels(k, meta["phase_to_truth"], LABELERS["valley"].names)
    assert any("=" in n for n in names), names  # the smoke run's phases were matched to true ones
    (ax,) = [a for a in kept["tool_path_by_phase.png"].axes if a.name == "3d"]
    assert any(isinstance(c, Poly3DCollection) for c in ax.collections)
    assert {c.get_label() for c in ax.collections} >= {"start", "end", "valley plates"}
    legend = [t.get_text() for lg in kept["tool_path_by_phase.png"].legends for t in lg.get_texts()]
    assert set(names) <= set(legend), legend
    repro = kept["reproduction_00_force_phase_alpha.png"]
    report = json.loads((run_dir / "report.json").read_text())["reproductions"][0]["phases"]
    assert f"online phase accuracy {report['accuracy']:.1%} over {report['updates']} estimates" in \
        repro._suptitle.get_text()
    legend = [t.get_text() for a in repro.axes if a.get_legend() for t in a.get_legend().get_texts()]
    assert set(names) <= set(legend), legend


def test_the_html_report_embeds_every_figure(run_dir):
    page = (run_dir / "report.html").read_text()
    images = page.count('src="data:image/png;base64,')
    assert images == len(FIGURES)  # no timing plot: in lockstep its histograms are the host's
    first = page.index("data:image/png;base64,") + len("data:image/png;base64,")
    assert base64.b64decode(page[first:page.index('"', first)]).startswith(PNG)
    assert "smoke" in page and "Number of phases" in page and "Reproductions" in page


def test_the_page_drawn_from_the_folder_is_the_page_the_run_wrote_from_its_report(drawn_run, tmp_path):
    """The run hands the page its report and text; etar-bench figures reads them back."""
    from services.results.html import write_html

    run_dir, _, page = drawn_run
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    (copy / "report.html").unlink()
    write_html(copy)
    assert (copy / "report.html").read_text() == page


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (make test installs Debian's chromium as root)")
def test_the_html_report_renders_in_a_headless_browser_with_every_image_loaded(run_dir, tmp_path):
    dom = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                          "--disable-background-networking", "--disable-component-update", "--disable-sync",
                          f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=5000", "--dump-dom",
                          (run_dir / "report.html").as_uri()], capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0, dom.stderr[-2000:]
    n = len(FIGURES)
    assert f'data-images="{n}/{n}"' in dom.stdout, dom.stdout[:500]


def test_compare_scores_etar_against_star_on_the_runs_demonstrations_and_draws_fig_26(run_dir, capsys):
    import json

    assert bench_cli.main(["compare", str(run_dir), "--seeds", "1"]) == 0
    out = capsys.readouterr().out
    assert "the thesis' claim" in out and "cannot be judged from one seed (in direction it" in out
    result = json.loads((run_dir / "comparison.json").read_text())
    assert set(result["summary"]) == {"ETAR", "STAR"} and result["demonstrations"] == 2
    assert [e["transitions"] for e in result["evaluations"]] == ["effect", "state"]
    for e in result["evaluations"]:
        assert 0.0 <= e["filtered"]["accuracy"] <= 1.0 and e["error_near_transitions"] >= 0.0
    assert (run_dir / "figures" / "etar_vs_star_phases.png").read_bytes().startswith(PNG)
    assert bench_cli.main(["compare", str(run_dir), "--seeds", "0"]) == 2
    # Table C1's check: the run's two demonstrations learned separately, phases matched
    c1 = result["table_c1"]
    assert c1["demonstrations"] == [0, 1] and sorted(c1["between_demonstrations"][0]["permutation"]) == [0, 1, 2]
    assert all(c1["summary"][k]["between_demonstrations"]["mean"] >= 0.0 for k in ("A", "B", "Sigma", "W"))
    assert c1["summary"]["A"]["between_seeds"] is None  # one seed: no spread between seeds
    assert "Table C1 check: demonstrations 0 and 1" in (run_dir / "comparison.txt").read_text()
    for bad in ("0", "0,0", "0,2", "a,b"):
        assert bench_cli.main(["compare", str(run_dir), "--seeds", "1", "--pair", bad]) == 2, bad


def test_compare_of_a_run_whose_demonstration_is_cut_short_names_the_file(run_dir, tmp_path, capsys):
    """A damaged recording is one line naming it, exit 2 (it was a RecordingError's traceback)."""
    import shutil

    damaged = tmp_path / "damaged"
    shutil.copytree(run_dir, damaged)
    recording = damaged / "recordings" / "demonstration_00.mcap"
    recording.write_bytes(recording.read_bytes()[:recording.stat().st_size // 2])
    capsys.readouterr()
    assert bench_cli.main(["compare", str(damaged), "--seeds", "1"]) == 2
    said = capsys.readouterr().err.strip().splitlines()
    assert len(said) == 1 and said[0].startswith(f"etar-bench compare: error: {recording}: incomplete recording"), said
