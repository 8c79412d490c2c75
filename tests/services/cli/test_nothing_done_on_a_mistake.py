"""A mistake on etar-bench's command line is refused before anything is made (no --out
folder left behind), the flags it takes do what they say, and what a command writes lands at
exactly the path given.  The one-line refusals themselves are rows of tests/test_mistakes.py."""

import errno
import tempfile
from argparse import Namespace

import numpy as np
import pytest

from services.cli import bench as bench_cli
from services.cli.run_commands import run_zenoh, write_demonstration


def refused(capsys, argv) -> str:
    try:
        code = bench_cli.main(argv)
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1, (code, lines)
    return lines[0]


@pytest.mark.parametrize("argv", [
    ["--param", "cell.nosuch=1"], ["--param", "cell.sensor_noise=1,-1"], ["--cluster", "garbage"],
    ["--cluster", "tcp://10.0.0.5:99999"], ["--repeats", "0"], ["--repeats", "10001"], ["--workers", "100000"],
    ["--param", "cell.sensor_noise=1,2,3", "--repeats", "4000"],
], ids=lambda argv: " ".join(argv))
def test_a_refused_sweep_makes_no_folder(capsys, tmp_path, argv):
    out = tmp_path / "sweep"
    line = refused(capsys, ["sweep", "scenarios/smoke.yaml", "--out", str(out), *argv])
    assert line.startswith("etar-bench sweep: error: ") and argv[0] in line, line
    assert not out.exists()


def test_too_many_runs_are_counted_before_any_is_planned(capsys, tmp_path):
    line = refused(capsys, ["sweep", "scenarios/smoke.yaml", "--out", str(tmp_path / "s"),
                            "--param", "cell.sensor_noise=1,2,3", "--repeats", "4000"])
    assert line.endswith("--param values x --repeats 4000 make 12000 runs, more than a sweep's 10000 (split it "
                         "into sweeps of their own)"), line


def zenoh_args(argv):
    return bench_cli.build_parser().parse_args(["run", "scenarios/smoke.yaml", *argv])


def test_the_run_joins_the_session_connect_names_with_every_zenoh_flag():
    options = run_zenoh(zenoh_args(["--connect", "tcp/127.0.0.1:7000", "--mode", "client", "--listen",
                                    "tcp/127.0.0.1:0", "--cfg", "transport/unicast/lowlatency:true"]))
    assert (options.mode, options.connect, options.listen, options.cfg) == (
        "client", ("tcp/127.0.0.1:7000",), ("tcp/127.0.0.1:0",), (("transport/unicast/lowlatency", "true"),))
    assert run_zenoh(zenoh_args([])) is None  # the runner's own session on loopback


def test_the_environments_zenoh_mode_is_a_default_not_a_choice(monkeypatch):
    """$ETAR_ZENOH_MODE is the services' default: a run without --connect is not refused for it."""
    monkeypatch.setenv("ETAR_ZENOH_MODE", "client")
    monkeypatch.setenv("ETAR_ZENOH_CONNECT", "garbage")  # nor for the services' default endpoint
    assert run_zenoh(zenoh_args([])) is None
    assert run_zenoh(zenoh_args(["--connect", "tcp/127.0.0.1:7000"])).mode == "client"


@pytest.mark.parametrize("argv,says", [
    (["serve", "scenarios/smoke.yaml", "--max-seconds", "-5"], "etar-bench serve: error: --out: required"),
    (["run", "--bogus"], "etar-bench run: error: --bogus: not a flag of this program"),
    (["--bogus"], "etar-bench: error: --bogus: not a flag of this program"),
    (["--bogus", "check", "scenarios/smoke.yaml"], "etar-bench: error: --bogus: not a flag of this program"),
    # before a command whose own argument is missing: the flag, not "scenario: required"
    (["--bogus", "run"], "etar-bench: error: --bogus: not a flag of this program"),
    (["--version", "--bogus", "run", "--", "x"], "etar-bench: error: --bogus: not a flag of this program"),
])
def test_a_flag_of_no_program_is_named_before_a_missing_argument_and_a_value_is_no_flag(capsys, argv, says):
    assert refused(capsys, argv).startswith(says)


def test_the_demonstrations_arrays_are_written_at_exactly_the_path_given(tmp_path, capsys):
    demo = dict(states=np.zeros((5, 3)), forces=np.ones((5, 3)), phases=np.zeros(4, dtype=int), dt=0.01,
                t=np.arange(5) * 0.01)
    path = tmp_path / "arrays"
    write_demonstration(Namespace(png=None, npz=str(path), world="valley", seed=0), demo)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arrays"]  # not arrays.npz beside it
    with np.load(path) as saved:
        assert saved["forces"].tolist() == demo["forces"].tolist()
    assert "once its name ends .npz" in capsys.readouterr().err


def test_a_demo_output_in_a_folder_nothing_can_be_made_in_is_refused_before_the_run(capsys, tmp_path, monkeypatch):
    """(root may write anywhere os.access asks about: the folder is asked by making one there)"""
    def read_only(*_, **__):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkdtemp", read_only)
    line = refused(capsys, ["demo", "--out", str(tmp_path / "run"), "--npz", str(tmp_path / "d.npz")])
    assert line == f"etar-bench demo: error: --npz {tmp_path / 'd.npz'}: cannot write in {tmp_path} " \
                   "(Read-only file system)"
    assert not (tmp_path / "run").exists()


def test_the_recorder_asks_the_folder_and_leaves_nothing_of_the_asking(tmp_path, monkeypatch):
    from services.nodes.recorder import RecorderConfig
    from services.runtime.config import FieldError

    RecorderConfig(out_dir=str(tmp_path / "run" / "recordings"))
    RecorderConfig(out_dir=str(tmp_path))
    assert list(tmp_path.iterdir()) == []

    def read_only(*_, **__):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkdtemp", read_only)
    with pytest.raises(FieldError, match=rf"cannot be made in {tmp_path} \(Read-only file system\)"):
        RecorderConfig(out_dir=str(tmp_path / "new"))
    with pytest.raises(FieldError, match=r"nothing can be made in that folder \(Read-only file system\)"):
        RecorderConfig(out_dir=str(tmp_path))
