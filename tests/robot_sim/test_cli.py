"""``robot-sim demo`` writes a picture and a recording that ``etar learn`` reads."""

import json

import numpy as np

from etar.cli import main as etar_main
from robot_sim.cli import main


def test_demo_writes_png_and_npz_that_etar_learns_from(tmp_path):
    png, npz = tmp_path / "valley.png", tmp_path / "valley.npz"
    assert main(["demo", "--world", "valley", "--side", "right", "--seed", "2", "--png", str(png),
                 "--npz", str(npz)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    with np.load(npz) as d:
        assert d["states"].shape[1] == 3 and d["forces"].shape == d["states"].shape
        assert d["phases"].shape == (len(d["states"]) - 1,)
        assert set(np.unique(d["phases"])) == {0, 1, 2}
        assert float(d["dt"]) == 0.01
    model = tmp_path / "model.json"
    assert etar_main(["learn", str(npz), "--phases", "3", "--out", str(model), "--restarts", "2"]) == 0
    assert json.loads(model.read_text())["n_phases"] == 3
