"""The ``etar`` command line: synth -> learn -> inspect, and its errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from etar.cli import main


def test_synth_learn_inspect(tmp_path, capsys):
    assert main(["synth", "--out", str(tmp_path), "--demos", "3", "--length", "300", "--phases", "2",
                 "--seed", "3"]) == 0
    demos = sorted(str(p) for p in tmp_path.glob("demo_*.npz"))
    assert len(demos) == 3
    model = tmp_path / "model.json"
    assert main(["learn", *demos, "--phases", "auto", "--max-phases", "3", "--out", str(model),
                 "--restarts", "2", "--selection", "pooled"]) == 0
    data = json.loads(model.read_text())
    assert data["n_phases"] == 2
    assert data["metadata"]["selection"]["best"] == 2
    assert set(data["metadata"]["selection"]["scores"]) == {"1", "2", "3"}
    assert len(data["metadata"]["impedance"]) == 2
    capsys.readouterr()
    assert main(["inspect", str(model), "--demos", *demos]) == 0
    out = capsys.readouterr().out
    assert "2 phases" in out and "BIC" in out and "accuracy" in out
    # the default: every demonstration chooses, the majority wins
    voted = tmp_path / "voted.json"
    assert main(["learn", *demos, "--max-phases", "3", "--out", str(voted), "--restarts", "2"]) == 0
    sel = json.loads(voted.read_text())["metadata"]["selection"]
    assert sel["method"] == "per_demonstration" and sel["best"] == 2 and len(sel["per_demonstration"]) == 3
    assert sum(sel["votes"].values()) == 3
    capsys.readouterr()
    assert main(["inspect", str(voted)]) == 0
    assert "demonstration 2:" in capsys.readouterr().out


def test_learn_fixed_number_of_phases(tmp_path):
    main(["synth", "--out", str(tmp_path), "--demos", "2", "--length", "200", "--phases", "2"])
    model = tmp_path / "m.json"
    assert main(["learn", *map(str, tmp_path.glob("*.npz")), "--phases", "3", "--out", str(model),
                 "--restarts", "1", "--max-iter", "10"]) == 0
    assert json.loads(model.read_text())["n_phases"] == 3


def test_errors_name_the_file_and_field(tmp_path, capsys):
    bad = tmp_path / "bad.npz"
    np.savez(bad, states=np.zeros((10, 3)))
    assert main(["learn", str(bad), "--out", str(tmp_path / "m.json")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "'forces' is missing" in err
    nan = tmp_path / "nan.npz"
    f = np.zeros((10, 3))
    f[4, 1] = np.nan
    np.savez(nan, states=np.zeros((10, 3)), forces=f)
    assert main(["learn", str(nan), "--out", str(tmp_path / "m.json")]) == 2
    assert f"{nan}: forces[4, 1] is nan" in capsys.readouterr().err
    assert main(["learn", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "m.json")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_console_script_help():
    out = subprocess.run([sys.executable, "-m", "etar.cli", "learn", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "--phases" in out.stdout


def test_learn_writes_to_a_relative_out_whose_folder_does_not_exist(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["synth", "--out", "demos", "--demos", "2", "--length", "200", "--phases", "2", "--seed", "1"]) == 0
    assert main(["learn", "demos/demo_00.npz", "demos/demo_01.npz", "--phases", "2", "--restarts", "1",
                 "--out", "new/folder/model.json"]) == 0
    data = json.loads((tmp_path / "new" / "folder" / "model.json").read_text())
    # the demonstrations are named as absolute paths: the file can be read from anywhere
    assert data["metadata"]["demonstrations"] == [str(tmp_path / "demos" / f"demo_0{i}.npz") for i in (0, 1)]


def test_etar_words_argparse_refusals_as_every_program_of_the_testbench_does(capsys):
    """One parser for every command line (etar.parsing): a flag's wrong value or an unknown
    subcommand is one line naming the flag and the value, exit 2."""

    for argv, said in ((["learn", "x.npz", "--out", "m.json", "--max-iter", "x"],
                        "etar learn: error: --max-iter x: expected an integer"),
                       (["bogus"], "etar: error: command bogus: not one of learn, inspect, synth")):
        with pytest.raises(SystemExit) as done:
            main(argv)
        assert done.value.code == 2
        assert capsys.readouterr().err.strip().splitlines() == [said]
