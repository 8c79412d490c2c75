"""``etar-bench demo``: one demonstration by the teacher, run by the nodes, writes a
picture and the arrays that ``etar learn`` reads; bad flags are one line and exit 2."""

import json

import numpy as np
import pytest

from etar.cli import main as etar_main
from services.cli.bench import main


@pytest.mark.slow
def test_demo_writes_png_and_npz_that_etar_learns_from(tmp_path, capsys):
    png, npz, out = tmp_path / "valley.png", tmp_path / "valley.npz", tmp_path / "run"
    assert main(["demo", "--world", "valley", "--side", "right", "--seed", "2", "--png", str(png),
                 "--npz", str(npz), "--out", str(out)]) == 0
    assert "Traceback" not in capsys.readouterr().err
    assert (out / "recordings" / "demonstration_00.mcap").is_file() and (out / "report.json").is_file()
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    with np.load(npz) as d:
        assert d["states"].shape[1] == 3 and d["forces"].shape == d["states"].shape
        assert d["phases"].shape == (len(d["states"]) - 1,)
        assert set(np.unique(d["phases"])) == {0, 1, 2}
        assert float(d["dt"]) == 0.01
    model = tmp_path / "model.json"
    assert etar_main(["learn", str(npz), "--phases", "3", "--out", str(model), "--restarts", "2"]) == 0
    assert json.loads(model.read_text())["n_phases"] == 3


@pytest.mark.parametrize("flags, names", [
    (["--world", "hose_coupler", "--side", "right"], "--side"),
    (["--max-seconds", "-1"], "--max-seconds"),
    (["--max-seconds", "0.001"], "--max-seconds"),  # under two of the learner's samples
    (["--spread", "nan"], "--spread"),
    (["--png", "{tmp}/missing/x.png"], "--png"),
])
def test_bad_flags_are_one_line_and_exit_2_before_anything_is_made(tmp_path, capsys, flags, names):
    out = tmp_path / "run"
    argv = ["demo", *(f.format(tmp=tmp_path) for f in flags), "--out", str(out)]
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("etar-bench demo: error: ") and names in lines[0], lines[0]
    assert "Traceback" not in captured.err and captured.out == ""
    assert not out.exists()
    assert not (tmp_path / "missing").exists()


@pytest.mark.slow
def test_a_demonstration_the_teacher_did_not_finish_exits_1_and_says_so(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["demo", "--max-seconds", "2", "--out", str(out)]) == 1
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("etar-bench demo: the teacher did not finish the task (the demonstration ended timeout)")
    assert (out / "recordings" / "demonstration_00.mcap").is_file()
