"""Every ordinary mistake on ``etar``'s command line is one stderr line naming the flag or
the file and the value, exit code 2, before anything is done; a run that fails after it
started is one line, exit code 1; never a traceback.  Also: the help of every option,
``--version``, the units ``inspect`` prints and the progress ``learn`` reports."""

import importlib.metadata
import json
import subprocess
import sys

import numpy as np
import pytest

from etar import cli
from etar.cli import main
from etar.model import ETAR
from etar.synthetic import make_task
from services.cli import etar as services_etar
from services.recordings.writer import EpisodeWriter
from services.runtime.messages import FT_WRENCH, ROBOT_CONTACT, ROBOT_STATE


def outcome(call, argv, capsys):
    """(exit code, the stderr lines) of one command, in this process."""
    try:
        code = call(argv)
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err.splitlines()


def refused(argv, capsys, call=main, code=2) -> str:
    """The one stderr line of a refused command (asserting the exit code)."""
    got, lines = outcome(call, argv, capsys)
    assert got == code, (got, lines)
    assert len(lines) == 1, lines
    return lines[0]


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    folder = tmp_path_factory.mktemp("demos")
    assert main(["synth", "--out", str(folder), "--demos", "3", "--length", "200", "--phases", "2",
                 "--seed", "3"]) == 0
    return sorted(str(p) for p in folder.glob("demo_*.npz"))


# --------------------------------------------------------------------------
# etar synth
# --------------------------------------------------------------------------


@pytest.mark.parametrize("flags,line", [
    (["--phases", "0"], "etar synth: error: --phases: must be an integer >= 1, got 0"),
    (["--demos", "0"], "etar synth: error: --demos: must be an integer >= 1, got 0"),
    (["--length", "1"], "etar synth: error: --length: must be an integer >= 4 (a sample more than one step per "
                        "phase of --phases 3), got 1"),
    (["--phases", "2", "--length", "2"], "etar synth: error: --length: must be an integer >= 3 (a sample more than "
                                         "one step per phase of --phases 2), got 2"),
    (["--seed", "-1"], "etar synth: error: --seed: must be an integer >= 0, got -1"),
    (["--phases", "x"], "etar synth: error: --phases x: expected an integer"),
    (["--demos", "1001"], "etar synth: error: --demos: must be an integer <= 1000, got 1001"),
    (["--length", "100001"], "etar synth: error: --length: must be an integer <= 100000, got 100001"),
])
def test_synth_refuses_a_bad_number(tmp_path, capsys, flags, line):
    out = tmp_path / "out"
    assert refused(["synth", "--out", str(out), *flags], capsys) == line
    assert not out.exists()  # nothing made


def test_synth_refuses_an_out_that_is_a_file_or_under_one(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert refused(["synth", "--out", str(afile / "sub")], capsys) == \
        f"etar synth: error: --out: {afile} is a file, not a folder, got '{afile}/sub'"
    assert refused(["synth", "--out", str(afile)], capsys) == \
        f"etar synth: error: --out: is a file, not a folder, got '{afile}'"
    assert afile.read_text() == "x"


def test_synth_makes_its_folder(tmp_path, capsys):
    assert main(["synth", "--out", str(tmp_path / "a" / "b"), "--demos", "1", "--length", "5", "--phases", "2"]) == 0
    assert [p.name for p in (tmp_path / "a" / "b").iterdir()] == ["demo_00.npz"]


# --------------------------------------------------------------------------
# etar learn: flags
# --------------------------------------------------------------------------


LEARN_FLAG_CASES = [
    (["--max-iter", "0"], "--max-iter: must be an integer >= 1, got 0"),
    (["--restarts", "0"], "--restarts: must be an integer >= 1, got 0"),
    (["--tol", "0"], "--tol: must be a finite number > 0 (nats per sample per iteration), got 0.0"),
    (["--tol=-1e-7"], "--tol: must be a finite number > 0 (nats per sample per iteration), got -1e-07"),
    (["--tol", "nan"], "--tol: must be a finite number > 0 (nats per sample per iteration), got nan"),
    (["--max-phases", "0"], "--max-phases: must be an integer >= 1, got 0"),
    (["--dt", "0"], "--dt: must be a finite number > 0 s, got 0.0"),
    (["--dt", "nan"], "--dt: must be a finite number > 0 s, got nan"),
    (["--phases", "x"], "--phases: must be 'auto' or an integer in 1..20, got 'x'"),
    (["--phases", "0"], "--phases: must be 'auto' or an integer in 1..20, got '0'"),
    (["--phases", "2.5"], "--phases: must be 'auto' or an integer in 1..20, got '2.5'"),
    (["--phases", "21"], "--phases: must be 'auto' or an integer in 1..20, got '21'"),
    (["--phases", "20"], "--phases: a 20-phase model has 2136 free parameters, more than the 597 steps of the "
                         "demonstrations (record more or use fewer phases), got 20"),
    (["--seed", "-3"], "--seed: must be an integer >= 0, got -3"),
    (["--criterion", "xic"], "--criterion xic: not one of bic, aic"),
    (["--max-iter", "many"], "--max-iter many: expected an integer"),
]


@pytest.mark.parametrize("flags,says", LEARN_FLAG_CASES, ids=[" ".join(f) for f, _ in LEARN_FLAG_CASES])
def test_learn_refuses_a_bad_flag_before_fitting(tmp_path, capsys, monkeypatch, demos, flags, says):
    monkeypatch.setattr(ETAR, "fit", lambda *a, **k: pytest.fail("fitted despite a bad flag"))
    out = tmp_path / "m.json"
    assert refused(["learn", *demos, "--out", str(out), *flags], capsys) == f"etar learn: error: {says}"
    assert not out.exists()


def test_learn_refuses_an_out_it_cannot_write_before_fitting(tmp_path, capsys, monkeypatch, demos):
    monkeypatch.setattr(ETAR, "fit", lambda *a, **k: pytest.fail("fitted despite a bad --out"))
    folder = tmp_path / "adir"
    folder.mkdir()
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert refused(["learn", *demos, "--out", str(folder)], capsys) == \
        f"etar learn: error: --out: is a folder; give the model file to write, got '{folder}'"
    assert refused(["learn", *demos, "--out", str(afile / "m.json")], capsys) == \
        f"etar learn: error: --out: {afile} is a file, not a folder, got '{afile}/m.json'"
    assert refused(["learn", *demos, "--out", str(afile / "deeper" / "m.json")], capsys) == \
        f"etar learn: error: --out: {afile} is a file, not a folder, got '{afile}/deeper/m.json'"
    assert refused(["learn", *demos, "--out", demos[1]], capsys) == \
        f"etar learn: error: --out: is one of the demonstration files; it would be overwritten, got '{demos[1]}'"
    assert refused(["learn", *demos, "--out", ""], capsys) == \
        "etar learn: error: --out: an empty path names no file or folder, got ''"


def test_an_out_in_a_folder_nothing_can_be_made_in_is_refused_before_any_work(tmp_path, capsys, monkeypatch, demos):
    """(root may write anywhere os.access asks about, /proc included: the folder is asked by
    making one there)"""
    import errno
    import tempfile

    def read_only(*_, **__):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(ETAR, "fit", lambda *a, **k: pytest.fail("fitted despite a bad --out"))
    monkeypatch.setattr(tempfile, "mkdtemp", read_only)
    assert refused(["learn", *demos, "--out", str(tmp_path / "m.json")], capsys) == \
        f"etar learn: error: --out: cannot write in {tmp_path} (read-only file system), got '{tmp_path}/m.json'"
    assert refused(["synth", "--out", str(tmp_path / "new")], capsys) == \
        f"etar synth: error: --out: cannot write in {tmp_path} (read-only file system), got '{tmp_path}/new'"
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------
# etar learn: files
# --------------------------------------------------------------------------


def test_learn_refuses_a_bad_file_in_one_line(tmp_path, capsys, demos):
    out = str(tmp_path / "m.json")
    missing = tmp_path / "missing.npz"
    assert refused(["learn", demos[0], str(missing), "--out", out], capsys) == \
        f"etar learn: error: {missing}: no such file"
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    assert refused(["learn", str(text), "--out", out], capsys, call=services_etar.main) == \
        f"etar learn: error: {text}: unsupported demonstration file type (expected .mcap or .npz), got suffix '.txt'"
    assert refused(["learn", str(tmp_path), "--out", out], capsys) == \
        f"etar learn: error: {tmp_path}: is a folder, not a demonstration file (give its files: {tmp_path}/*.npz)"
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"PK\x03\x04 not really a zip archive")
    line = refused(["learn", str(corrupt), "--out", out], capsys)
    assert line.startswith(f"etar learn: error: {corrupt}: not a readable .npz file (")
    wide = tmp_path / "wide.npz"
    np.savez(wide, states=np.zeros((50, 6)), forces=np.zeros((50, 3)))
    assert refused(["learn", demos[0], str(wide), "--out", out], capsys) == \
        f"etar learn: error: {wide}: states has 6 columns, expected 3 (shape (50, 6)) (as in {demos[0]})"
    short = tmp_path / "short.npz"
    np.savez(short, states=np.zeros((1, 3)), forces=np.zeros((1, 3)))
    assert refused(["learn", str(short), "--out", out], capsys) == \
        f"etar learn: error: {short}: needs at least 2 samples, got 1"
    bad_dt = tmp_path / "bad_dt.npz"
    np.savez(bad_dt, states=np.random.default_rng(0).normal(size=(80, 3)), forces=np.zeros((80, 3)), dt=0.0)
    assert refused(["learn", str(bad_dt), "--out", out], capsys) == \
        f"etar learn: error: {bad_dt}: field 'dt' must be a sample period > 0 s (or pass --dt), got 0.0"
    assert not (tmp_path / "m.json").exists()


def test_learn_refuses_demonstrations_too_short_for_any_model(tmp_path, capsys):
    rng = np.random.default_rng(0)
    paths = []
    for i, samples in enumerate((20, 20, 10, 10)):
        paths.append(str(tmp_path / f"d{i}.npz"))
        np.savez(paths[-1], states=rng.normal(size=(samples, 3)), forces=rng.normal(size=(samples, 3)))
    out = str(tmp_path / "m.json")
    assert refused(["learn", paths[0], paths[1], "--out", out], capsys) == \
        (f"etar learn: error: {paths[0]}: has 20 samples: its 19 steps are fewer than the 27 free parameters of "
         "even a 1-phase model, and each demonstration chooses its number of phases alone (--selection pooled "
         "scores them together)")
    assert refused(["learn", paths[0], "--out", out], capsys) == \
        f"etar learn: error: {paths[0]}: its 19 steps are fewer than the 27 free parameters of even a 1-phase " \
        "model, got '20 samples'"
    assert refused(["learn", paths[2], paths[3], "--selection", "pooled", "--out", out], capsys) == \
        "etar learn: error: DEMOS: their 18 steps are fewer than the 27 free parameters of even a 1-phase model, " \
        f"got {[paths[2], paths[3]]!r}"


def test_a_run_that_fails_after_it_started_is_one_line_and_exit_1(tmp_path, capsys, monkeypatch, demos):
    def diverge(*args, **kwargs):
        raise FloatingPointError("log-likelihood became nan at iteration 3; check for duplicated or constant data")

    monkeypatch.setattr(ETAR, "fit", diverge)
    assert refused(["learn", *demos, "--phases", "2", "--out", str(tmp_path / "m.json")], capsys, code=1) == \
        "etar learn: error: log-likelihood became nan at iteration 3; check for duplicated or constant data"


# --------------------------------------------------------------------------
# recordings: a reproduction is not a demonstration
# --------------------------------------------------------------------------


def write_recording(path, kind: str, cycles: int = 600, seed: int = 0):
    """A finished recording of ``cycles`` robot cycles (1 ms apart) with the three
    topics a demonstration is made of, its metadata saying ``kind``."""
    rng = np.random.default_rng(seed)
    position = np.cumsum(rng.normal(scale=1e-4, size=(cycles, 3)), axis=0) + [0.5, 0.0, 0.4]
    with EpisodeWriter(path, run_id="r1", episode_kind=kind, episode_index=0) as w:
        for seq in range(1, cycles + 1):
            head = dict(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=seq * 1000)
            t = seq * 1_000_000
            cart = np.concatenate([np.eye(3), position[seq - 1][:, None]], axis=1).reshape(-1)
            w.add("etar/r1/robot/state", ROBOT_STATE.encode(
                **head, reflected_seq=seq - 1, fri_state=2, fri_quality=3, control_mode=2, msr_jnt_pos=np.zeros(7),
                msr_cart_pos=cart, est_ext_tcp_ft=np.zeros(6), answer_rate=1.0, latency_s=2e-4, jitter_s=1e-5,
                miss_rate=0.0, safety=0, gravity_compensation=True, episode=0), t)
            wrench = rng.normal(size=6)
            w.add("etar/r1/ft/wrench", FT_WRENCH.encode(
                **head, rdt_sequence=seq, ft_sequence=seq, status=0, counts=[int(x) for x in wrench * 1e6],
                counts_per_force=1e6, counts_per_torque=1e6, wrench=wrench), t + 1)
            w.add("etar/r1/robot/contact", ROBOT_CONTACT.encode(
                **head, wrench=wrench, contact_force=np.zeros(3), touching=[], true_phase=0, episode=0), t + 2)
    return path


def test_learn_refuses_a_reproduction_recording_and_names_it(tmp_path, capsys, monkeypatch):
    demonstration = write_recording(tmp_path / "demonstration_00.mcap", "demonstration")
    reproduction = write_recording(tmp_path / "reproduction_00.mcap", "reproduction")
    assert services_etar.recording_kind(reproduction) == "reproduction"
    assert services_etar.recording_kind(demonstration) == "demonstration"
    with monkeypatch.context() as patch:
        patch.setattr(ETAR, "fit", lambda *a, **k: pytest.fail("fitted a reproduction"))
        line = refused(["learn", str(demonstration), str(reproduction), "--phases", "1", "--out",
                        str(tmp_path / "m.json")], capsys, call=services_etar.main)
    assert line == (f"etar learn: error: {reproduction}: is a reproduction recording, not a demonstration "
                    "(its metadata's episode_kind), got 'reproduction'")
    # the same data as a demonstration is learned from; and inspect segments a reproduction
    model = tmp_path / "m.json"
    assert services_etar.main(["learn", str(demonstration), "--phases", "1", "--restarts", "1", "--max-iter", "5",
                               "--out", str(model)]) == 0
    assert json.loads(model.read_text())["metadata"]["demonstrations"] == [str(demonstration)]
    capsys.readouterr()
    assert services_etar.main(["inspect", str(model), "--demos", str(reproduction)]) == 0
    assert f"{reproduction}: phases [0]" in capsys.readouterr().out


def test_a_bad_recording_is_one_line(tmp_path, capsys):
    out = str(tmp_path / "m.json")
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"garbage" * 10)
    assert services_etar.recording_kind(garbage) is None
    line = refused(["learn", str(garbage), "--out", out], capsys, call=services_etar.main)
    assert line.startswith(f"etar learn: error: {garbage}: not a readable MCAP file (")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert refused(["learn", str(empty), "--out", out], capsys, call=services_etar.main) == \
        f"etar learn: error: {empty}: not an MCAP file (0 bytes)"
    missing = tmp_path / "missing.mcap"
    assert refused(["learn", str(missing), "--out", out], capsys, call=services_etar.main) == \
        f"etar learn: error: {missing}: no such file"


# --------------------------------------------------------------------------
# etar inspect
# --------------------------------------------------------------------------


def test_inspect_refuses_a_missing_or_garbage_model_in_one_line(tmp_path, capsys, demos):
    missing = tmp_path / "missing.json"
    assert refused(["inspect", str(missing)], capsys) == f"etar inspect: error: {missing}: no such model file"
    garbage = tmp_path / "garbage.json"
    garbage.write_text("{not json")
    line = refused(["inspect", str(garbage)], capsys)
    assert line.startswith(f"etar inspect: error: {garbage}: not a JSON model file (")
    other = tmp_path / "other.json"
    other.write_text('{"format": "something else"}')
    assert refused(["inspect", str(other)], capsys) == \
        f"etar inspect: error: {other}: field 'format' is 'something else', expected 'etar-model'"
    assert refused(["inspect", str(tmp_path)], capsys).startswith(
        f"etar inspect: error: {tmp_path}: cannot read the model file (")
    narrow = tmp_path / "narrow.json"
    make_task(2, n=2, m=3).model.save(narrow)
    assert refused(["inspect", str(narrow), "--demos", demos[0]], capsys) == \
        f"etar inspect: error: {demos[0]}: states has 3 columns, expected 2 (shape (200, 3)) (as the model {narrow})"


def test_inspect_names_the_units_of_the_prediction_error(tmp_path, capsys, demos):
    model = tmp_path / "m.json"
    assert main(["learn", *demos, "--phases", "2", "--restarts", "1", "--max-iter", "5", "--out", str(model)]) == 0
    assert json.loads(model.read_text())["metadata"]["state"] == "position"
    capsys.readouterr()
    assert main(["inspect", str(model), "--demos", *demos]) == 0
    out = capsys.readouterr().out
    assert "state units" not in out
    assert "one-step prediction error (mean over steps of the squared error summed over the state columns, m²)" in out
    assert "noise std per state dimension (m) = " in out
    # a model whose metadata does not name its state: no unit is made up
    bare = tmp_path / "bare.json"
    make_task(2, n=2, m=2).model.save(bare)
    rng = np.random.default_rng(0)
    two = tmp_path / "two.npz"
    np.savez(two, states=rng.normal(size=(50, 2)), forces=rng.normal(size=(50, 2)))
    assert main(["inspect", str(bare), "--demos", str(two)]) == 0
    out = capsys.readouterr().out
    assert "squared units of the state columns)" in out and "m²" not in out


def test_the_units_of_a_pose_state():
    model = make_task(1, n=6, m=6).model
    model.metadata["state"] = "pose"
    assert cli.state_units(model) == ("m for the position columns, rad for the rotation vector's",
                                      "m² for the position columns plus rad² for the rotation vector's")


# --------------------------------------------------------------------------
# help, --version, progress
# --------------------------------------------------------------------------


def test_every_option_has_help_and_every_out_says_file_or_folder():
    parser = cli.build_parser()
    commands = next(a for a in parser._actions if a.dest == "command").choices
    for name, sub in commands.items():
        for action in sub._actions:
            assert action.help, f"etar {name} {action.option_strings or action.dest} has no help"
    outs = {name: next(a for a in sub._actions if "--out" in a.option_strings).help
            for name, sub in commands.items() if any("--out" in a.option_strings for a in sub._actions)}
    assert outs == {"learn": "model file to write (JSON); its folder is created, an existing file replaced",
                    "synth": "folder to write demo_XX.npz into (created; existing demo_XX.npz are replaced)"}
    # the help's numbers are the model's defaults
    model = ETAR(1)
    learn = " ".join(commands["learn"].format_help().split())
    assert f"each run for {model.init_iter} EM iterations" in learn and f"after its {model.init_iter}" in learn
    assert f"averaged over {model.window} iterations" in learn


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"etar {importlib.metadata.version('etar-testbench')}"


def test_version_of_an_uninstalled_package(monkeypatch):
    def not_installed(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", not_installed)
    assert cli._version() == "unknown"


def test_learn_reports_each_candidate_fit_and_the_restarts(tmp_path, capsys, demos):
    assert main(["learn", *demos, "--max-phases", "2", "--restarts", "2", "--max-iter", "20",
                 "--out", str(tmp_path / "v.json")]) == 0
    err = capsys.readouterr().err
    for i, label in enumerate(["K=1 demonstration 0", "K=2 demonstration 0", "K=1 demonstration 1",
                               "K=2 demonstration 1", "K=1 demonstration 2", "K=2 demonstration 2"], 1):
        assert f"fit {i}/6 done: {label}, log-likelihood " in err
    assert "restart 2/2: objective" in err and "EM iterations in all" in err
    assert main(["learn", *demos, "--max-phases", "2", "--restarts", "1", "--max-iter", "20", "--selection", "pooled",
                 "--out", str(tmp_path / "p.json")]) == 0
    err = capsys.readouterr().err
    assert "fit 1/2 done: K=1, log-likelihood" in err and "fit 2/2 done: K=2, log-likelihood" in err
    assert main(["learn", *demos, "--phases", "2", "--restarts", "1", "--max-iter", "110", "--tol", "1e-30",
                 "--out", str(tmp_path / "f.json")]) == 0
    err = capsys.readouterr().err
    assert "  EM iteration 50/110: objective" in err and "  EM iteration 100/110: objective" in err
    assert "restart 1/1: objective" in err


def test_the_console_script_refuses_in_one_line(tmp_path):
    """The installed ``etar``, in its own process: exit code 2, one line, nothing made."""
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, "-m", "services.cli.etar", "synth", "--out", str(out), "--phases", "0"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert done.stderr.splitlines() == ["etar synth: error: --phases: must be an integer >= 1, got 0"]
    assert not out.exists()


def test_the_learn_stage_reports_each_candidate_fit_from_its_pool(demos):
    """The scenario runner's learn stage says ``fit i/N done`` as the fits come back
    from its process pool, and the pool changes nothing in the model."""
    from services.run.learn import _fit
    from services.runtime.threads import process_map
    from services.scenario import LearnStage

    loaded = [dict(np.load(p)) for p in demos]
    stage = LearnStage(phases="auto", candidates=(1, 2), restarts=1, max_iter=20, seed=0)
    heard = {}
    for workers in (1, 2):
        heard[workers] = []
        with process_map(workers) as work_map:
            (model,), _ = _fit(stage, loaded, work_map, heard[workers].append)
        heard[workers].append(model.to_dict())
    for i, label in enumerate(["K=1 demonstration 0", "K=2 demonstration 0", "K=1 demonstration 1"], 1):
        assert any(line.startswith(f"fit {i}/6 done: {label}, ") for line in heard[2]), heard[2]
    for record in heard.values():
        record[-1]["fit"].pop("seconds")
    assert heard[1][-1] == heard[2][-1]
