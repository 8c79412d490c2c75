"""Every ordinary mistake a user has been seen to make, answered in one line that names
the flag or the file and the value, before any work is done: exit code 2 for a usage
error, 1 for a run that failed, never a traceback.  The table below is docs/mistakes.md
(``python -m tests.test_mistakes > docs/mistakes.md`` writes it again).

Each command is what a user types, run through its console script's own function (the
one pyproject.toml names), with the placeholders in capitals standing for the files the
fixture below makes."""

from __future__ import annotations

import json
import shlex
import sys
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "mistakes.md"

# (command, exit code, what its one line says); placeholders: FILE an existing file, DIR an
# existing folder, RUN_DIR a finished run's folder, FAILED_RUN a failed run's, FAR.yaml,
# LOW.yaml, NO_MODEL.yaml, BAD_MODEL.yaml, SHORT.yaml scenarios with the mistake their name says,
# DEMO.npz a demonstration, REPRO.mcap a reproduction's recording, SWEEP_DIR a sweep's folder
CASES = [
    # etar-bench run
    ("etar-bench run scenarios/smoke.yaml --out FILE", 2, "--out FILE: FILE is a file; --out names the run's folder"),
    ("etar-bench run scenarios/smoke.yaml --out RUN_DIR", 2,
     "--out RUN_DIR: RUN_DIR already holds a run; choose another folder, or --replace to remove that run first"),
    ("etar-bench run scenarios/smoke.yaml --out SWEEP_DIR --replace", 2,
     "--out SWEEP_DIR: SWEEP_DIR is a sweep's folder (SWEEP_DIR/sweep.json); choose a folder of the run's own"),
    ("etar-bench run scenarios/smoke.yaml --out SWEEP_DIR/runs", 2,
     "--out SWEEP_DIR/runs: SWEEP_DIR/runs is part of a sweep's folder (SWEEP_DIR/sweep.json); choose a folder of "
     "the run's own"),
    ("etar-bench run scenarios/smoke.yaml --ready-timeout -5", 2,
     "--ready-timeout must be a number of seconds > 0, got -5.0"),
    ("etar-bench run NO_MODEL.yaml", 2, "NO_MODEL.yaml: model: the model file does not exist, got 'DIR/nosuch.json'"),
    ("etar-bench run BAD_MODEL.yaml", 2, "BAD_MODEL.yaml: model: the model file does not load"),
    ("etar-bench run FAR.yaml", 2, "FAR.yaml: stages[0].demonstrate.start: demonstration 1 (left side) would start "
                                   "at a point the arm cannot reach"),
    ("etar-bench run LOW.yaml", 2, "LOW.yaml: stages[0].demonstrate.start: demonstration 1 (left side) would start "
                                   "at z = -0.101 m, at or below the floor"),
    ("etar-bench run scenarios/smoke.yaml --bogus", 2, "--bogus: not a flag of this program"),
    ("etar-bench run scenarios/smoke.yaml --ros2 300", 2,
     "--ros2 DOMAIN: a ROS 2 domain id is an integer in 0..232, got 300"),
    ("etar-bench run scenarios/smoke.yaml --transport inproc --ros2", 2,
     "--ros2 puts the cell on ROS 2's Zenoh wire beside the services' own: it needs --transport zenoh"),
    ("etar-bench run scenarios/smoke.yaml --ros2 --ros2-clock-rate-hz 300", 2,
     "--ros2-clock-rate-hz must divide the FRI rate 1000 Hz"),
    ("etar-bench run scenarios/smoke.yaml --wire udp", 2, "scenarios/smoke.yaml: clock: --wire udp needs the "
                                                         "realtime clock (--clock realtime)"),
    ("etar-bench run scenarios/smoke.yaml --out ''", 2, "--out '': an empty path; --out names the run's folder"),
    ("etar-bench run scenarios/smoke.yaml --listen tcp/127.0.0.1:-1", 2,
     "--listen tcp/127.0.0.1:-1: port '-1' is not in 0..65535 (0: any free port)"),
    ("etar-bench run scenarios/smoke.yaml --cfg nocolon", 2, "--cfg nocolon: expected KEY:VALUE"),
    ("etar-bench run scenarios/smoke.yaml --listen tcp/127.0.0.1:0", 2,
     "--listen tcp/127.0.0.1:0: needs --connect ENDPOINT: the runner and its services share the Zenoh flags only "
     "on a session they join; without --connect the runner makes its own on loopback"),
    ("etar-bench run scenarios/smoke.yaml --mode client", 2, "--mode client: needs --connect ENDPOINT"),
    ("etar-bench run scenarios/smoke.yaml --transport inproc --connect tcp/127.0.0.1:7447", 2,
     "--connect tcp/127.0.0.1:7447: a Zenoh flag; --transport inproc runs every node in this process, without "
     "Zenoh: it needs --transport zenoh"),
    ("etar-bench --bogus", 2, "--bogus: not a flag of this program"),
    ("etar-bench --bogus run", 2, "--bogus: not a flag of this program"),
    # etar-bench serve
    ("etar-bench serve scenarios/smoke.yaml --out DIR/served --fri-remote nonsense", 2,
     "--fri-remote 'nonsense': expected HOST:PORT, e.g. 127.0.0.1:49938"),
    ("etar-bench serve scenarios/smoke.yaml --out DIR/served --start 2,0,0.3", 2,
     "--start 2,0,0.3: a point the arm cannot reach with the tool pointing down"),
    ("etar-bench serve scenarios/smoke.yaml --out DIR/served --netft example.org", 2,
     "--netft example.org: not an IPv4 address"),
    ("etar-bench serve scenarios/smoke.yaml --out DIR/served --krl testbench", 2,
     "--krl testbench: not one of frilibrary, lwr_hw"),
    ("etar-bench serve scenarios/smoke.yaml --out DIR/served --max-seconds 1e12", 2,
     "--max-seconds must be a number of seconds > 0 and <= 3600, got 1000000000000.0"),
    ("etar-bench serve scenarios/smoke.yaml --out DIR/served --robot-flag=--bogus", 2,
     "--robot-flag --bogus: not a flag of etar-robot"),
    # etar-bench check
    ("etar-bench check FAR.yaml", 2, "would start at a point the arm cannot reach with the tool pointing down"),
    ("etar-bench check NO_MODEL.yaml", 2, "model: the model file does not exist"),
    ("etar-bench check TRUTH7.yaml", 2, "TRUTH7.yaml: model: the model matches its phase 0 to true phase 7; the "
                                        "valley world's true phases are 0..2 (free motion, sliding along a plate, "
                                        "sliding along the groove) (metadata.phase_to_truth)"),
    ("etar-bench check FILE", 2, "FILE: the file is empty"),
    ("etar-bench check SHORT.yaml", 2, "stages[0].demonstrate.max_seconds: a demonstration is recorded at 100 Hz for "
                                       "the learner: expected at least 0.02 s (two samples), got 0.001"),
    ("etar-bench check scenarios/smoke.yaml extra", 2, "extra: more arguments than this program takes (see --help)"),
    # etar-bench report / figures
    ("etar-bench report FAILED_RUN", 1, "etar-bench report: the run failed: RuntimeError: the recorder died"),
    ("etar-bench report DIR", 2, "DIR/report.txt not found (is DIR a run directory?)"),
    ("etar-bench figures DIR", 2, "DIR/report.json: missing (is DIR a finished run's folder?)"),
    # etar-bench sweep, demo, export, certs, router
    ("etar-bench sweep scenarios/smoke.yaml --workers 0 --out DIR/sweep", 2, "--workers must be >= 1, got 0"),
    ("etar-bench sweep scenarios/smoke.yaml --param reproduce[5].count=1 --out DIR/sweep", 2,
     "reproduce[5].count: the scenario has 1 reproduce stage(s), index 0..0, got 5"),
    ("etar-bench sweep scenarios/smoke.yaml --out FILE", 2, "--out FILE: FILE is a file; --out names the sweep's folder"),
    ("etar-bench sweep scenarios/smoke.yaml --out SWEEP_DIR", 2, "--out SWEEP_DIR: SWEEP_DIR already holds a sweep "
                                                                  "(sweep.json); choose another folder, or --replace"),
    ("etar-bench sweep scenarios/smoke.yaml --out RUN_DIR --replace", 2,
     "--out RUN_DIR: RUN_DIR holds a run (its report, recordings or model), not a sweep; choose another folder"),
    ("etar-bench compare RUN_DIR --seeds 100000000", 2, "--seeds must be 1..1000, got 100000000"),
    ("etar-bench compare RUN_DIR --pair -1,0", 2,
     "--pair: expected one value; -1,0 begins with '-', as a flag does: give it as --pair=-1,0"),
    ("etar-bench sweep scenarios/smoke.yaml --param cell.sensor_noise=, --out DIR/sweep", 2,
     "--param 'cell.sensor_noise=,': no values"),
    ("etar-bench sweep scenarios/smoke.yaml --param cell.sensor_noise=[1, --out DIR/sweep", 2,
     "--param cell.sensor_noise: value '[1,' is not YAML (expected the node content, but found '<stream end>')"),
    ("etar-bench sweep scenarios/smoke.yaml --out ''", 2, "--out '': an empty path; --out names the sweep's folder"),
    ("etar-bench sweep scenarios/smoke.yaml --repeats 99999999999999999999 --out DIR/sweep", 2,
     "--repeats must be <= 10000, got 99999999999999999999"),
    ("etar-bench sweep scenarios/smoke.yaml --workers 99999999999999 --out DIR/sweep", 2,
     "CPUs this process may use), got 99999999999999"),
    ("etar-bench sweep scenarios/smoke.yaml --cluster garbage --out DIR/sweep", 2,
     "--cluster garbage: no HOST:PORT; expected a Dask scheduler's address, e.g. tcp://10.0.0.5:8786"),
    ("etar-bench recover REPRO.mcap --out DIR", 2, "--out DIR: a folder; --out names the output file"),
    ("etar-bench recover REPRO.mcap --out DIR/missing/x.mcap", 2,
     "--out DIR/missing/x.mcap: its folder DIR/missing does not exist"),
    ("etar-bench demo --out FILE", 2, "--out FILE: FILE is a file; --out names the run's folder"),
    ("etar-bench demo --out RUN_DIR", 2, "--out RUN_DIR: RUN_DIR already holds a run; choose another folder, or "
                                         "--replace"),
    ("etar-bench recover DIR/nosuch.mcap", 2, "DIR/nosuch.mcap: no such file"),
    ("etar-bench export DIR --foxglove", 2, "DIR: no recordings/ folder: not a run's folder"),
    ("etar-bench export RUN_DIR", 2, "say what to export: --foxglove (visual topics added to the recordings) "
                                     "and/or --rosbag2"),
    ("etar-bench export RUN_DIR --rosbag2 --ros2-wrench-rate-hz 0", 2, "--ros2-wrench-rate-hz must divide"),
    ("etar-bench export RUN_DIR --rosbag2 --out ''", 2, "--out '': an empty path; --out names the folder for the bags"),
    ("etar-bench export RUN_DIR --rosbag2 --out /proc/bags", 2,
     "--out '/proc/bags': cannot make that folder (No such file or directory); --out names the folder for the bags"),
    ("etar-bench demo --max-seconds -1", 2, "--max-seconds: expected a finite number > 0, got -1.0"),
    ("etar-bench demo --spread nan", 2, "--spread: expected a finite number >= 0, got nan"),
    ("etar-bench demo --png DIR/missing/demo.png", 2, "--png DIR/missing/demo.png: the folder DIR/missing does not "
                                                      "exist"),
    ("etar-bench demo --world hose_coupler --side right", 2, "--side: the hose_coupler world has one side"),
    ("etar-bench demo --png DIR", 2, "--png DIR: a folder; --png names the file to write"),
    ("etar-bench demo --npz DIR", 2, "--npz DIR: a folder; --npz names the file to write"),
    ("etar-bench demo --npz /proc/x.npz", 2, "--npz /proc/x.npz: cannot write in /proc"),
    ("etar-bench demo --png ''", 2, "--png '': an empty path; --png names the file to write"),
    ("etar-bench export RUN_DIR --foxglove --visual-rate-hz 0", 2, "--visual-rate-hz"),
    ("etar-bench certs FILE", 2, "FILE: cannot make the credentials' folder there (a file of that name exists)"),
    ("etar-bench certs ''", 2, "'': an empty path; give the credentials' folder"),
    ("etar-bench router --listen garbage", 2, "--listen garbage: Endpoints must be of the form PROTOCOL/ADDRESS"),
    ("etar-bench router --listen tcp/127.0.0.1:99999", 2, "--listen tcp/127.0.0.1:99999: port '99999' is not in "
                                                          "0..65535"),
    ("etar-bench info FILE", 2, "FILE: not an MCAP file (0 bytes)"),
    ("etar-bench diff RUN_DIR DIR/nosuch", 2, "DIR/nosuch: no such folder"),
    # etar
    ("etar learn DEMO.npz --out DIR", 2, "--out: is a folder; give the model file to write, got 'DIR'"),
    ("etar learn DEMO.npz --out FILE/model.json", 2, "--out: FILE is a file, not a folder"),
    ("etar learn DEMO.npz --out DIR/m.json --max-iter 0", 2, "--max-iter: must be an integer >= 1, got 0"),
    ("etar learn DEMO.npz --out DIR/m.json --phases 0", 2, "--phases: must be 'auto' or an integer in 1..20, got '0'"),
    ("etar learn DEMO.npz --out DIR/m.json --max-phases 100000", 2, "--max-phases: must be an integer <= 20, got 100000"),
    ("etar learn REPRO.mcap --out DIR/m.json", 2, "REPRO.mcap: is a reproduction recording, not a demonstration"),
    ("etar learn DIR/missing.npz --out DIR/m.json", 2, "DIR/missing.npz: no such file"),
    ("etar learn DEMO.npz --out /proc/m.json", 2, "--out: cannot write in /proc"),
    ("etar synth --phases 0 --out DIR/synth", 2, "--phases: must be an integer >= 1, got 0"),
    ("etar synth --demos 0 --out DIR/synth", 2, "--demos: must be an integer >= 1, got 0"),
    ("etar synth --out FILE/sub", 2, "--out: FILE is a file, not a folder"),
    ("etar synth --out ''", 2, "--out: an empty path names no file or folder, got ''"),
    ("etar synth --out /proc/x", 2, "--out: cannot write in /proc (no such file or directory), got '/proc/x'"),
    ("etar synth --demos 99999999 --out DIR/synth", 2, "--demos: must be an integer <= 1000, got 99999999"),
    ("etar --bogus", 2, "--bogus: not a flag of this program"),
    ("etar --bogus learn", 2, "--bogus: not a flag of this program"),
    ("etar inspect FILE", 2, "FILE: not a JSON model file"),
    ("etar inspect DEEP.json", 2, "DEEP.json: not a JSON model file (nested too deeply)"),
    ("etar inspect BAD_TASK.json", 2, "BAD_TASK.json: metadata.impedance[0].successor: expected a phase 0..2 or "
                                      "null, got 99"),
    ("etar learn ARRAY.npz --out DIR/m.json", 2, "ARRAY.npz: not a .npz archive (a single array?)"),
    ("etar learn COMPLEX.npz --out DIR/m.json", 2, "COMPLEX.npz: states is complex (complex128); expected real "
                                                   "numbers"),
    ("etar learn HUGE.npz --out DIR/m.json", 2, "HUGE.npz: states[0, 0] is 1e+200; values past 1e+100 overflow the "
                                                "fit's sums of squares (wrong units?)"),
    ("etar learn LABELS.npz --out DIR/m.json", 2, "LABELS.npz: field 'phases' has 10 labels; expected one per "
                                                  "sample (50) or per step (49)"),
    ("etar learn DEMO.npz DTX.npz --out DIR/m.json", 2, "DTX.npz: field 'dt' must be a sample period > 0 s (or "
                                                        "pass --dt), got 'x'"),
    ("etar learn DEMO.npz DT2.npz --out DIR/m.json", 2, "DT2.npz: field 'dt' differs from DEMO.npz's 0.01 s: "
                                                        "demonstrations learned together must share their sample period"),
    # the services
    ("etar-robot --run-id x --world free_space", 2, "--world free_space: not one of"),
    ("etar-robot --run-id x --sched-fifo 1000", 2, "--sched-fifo 1000: a SCHED_FIFO priority is 1..99 (0: off)"),
    ("etar-robot --run-id x --sched-fifo -5", 2, "--sched-fifo -5: a SCHED_FIFO priority is 1..99 (0: off)"),
    ("etar-robot --run-id x --connect tcp/127.0.0.1:99999", 2,
     "--connect tcp/127.0.0.1:99999: port '99999' is not in 1..65535"),
    ("etar-robot --run-id x --seed -1", 2, "--seed -1: must be an integer >= 0"),
    ("etar-robot --run-id x --stall-every -1", 2, "--stall-every -1: must be a finite number >= 0"),
    ("etar-impedance-commander --run-id x --stall-ms -1", 2, "--stall-ms -1: must be a finite number >= 0"),
    ("etar-impedance-commander --run-id x --damping-ratio -1", 2, "--damping-ratio -1: must be a finite number > 0"),
    ("etar-robot --run-id x --answer-timeout inf", 2, "--answer-timeout inf: must be a finite number of seconds > 0"),
    ("etar-robot --bogus", 2, "--bogus: not a flag of this program"),
    ("etar-recorder --run-id x --out-dir FILE", 2, "--out-dir FILE: not a folder (it is a file)"),
    ("etar-recorder --run-id x --out-dir /proc/x", 2, "--out-dir /proc/x: cannot be made in /proc"),
    ("etar-recorder --run-id x --out-dir ''", 2, "--out-dir '': expected a folder"),
    ("etar-ft-sensor --run-id x --noise-scale -1", 2, "--noise-scale -1: must be a finite number >= 0"),
    ("etar-phase-estimator --run-id x --model DIR/nosuch.json", 2, "--model DIR/nosuch.json: no such file"),
    ("etar-robot", 2, "--run-id: required"),
]


def placeholders(base: Path) -> dict:
    """The files the commands name, made in ``base``."""
    p = {"FILE": base / "afile", "DIR": base, "RUN_DIR": base / "run", "FAILED_RUN": base / "failed"}
    p["FILE"].write_text("")
    p["SWEEP_DIR"] = base / "sweep"
    p["SWEEP_DIR"].mkdir()
    (p["SWEEP_DIR"] / "sweep.json").write_text("{}")
    scenario = "name: {name}\nworld: valley\n{model}stages:\n  - {stage}\n"
    for name, model, stage in (
            ("FAR", "", "demonstrate: {count: 1, start: [5.0, -0.1, 0.3]}"),
            ("LOW", "", "demonstrate: {count: 1, start: [0.5, -0.1, -0.1]}"),
            ("NO_MODEL", "model: nosuch.json\n", "reproduce: {count: 1}"),
            ("BAD_MODEL", "model: bad.json\n", "reproduce: {count: 1}"),
            ("TRUTH7", "model: truth7.json\n", "reproduce: {count: 1}"),
            ("SHORT", "", "demonstrate: {count: 1, max_seconds: 0.001}")):
        p[f"{name}.yaml"] = base / f"{name}.yaml"
        p[f"{name}.yaml"].write_text(scenario.format(name=name.lower(), model=model, stage=stage))
    (base / "bad.json").write_text("garbage")
    # the valley's model with its first phase matched to a true phase the valley does not have
    valley = json.loads((ROOT / "scenarios" / "models" / "valley.json").read_text())
    valley["metadata"]["phase_to_truth"]["0"] = 7
    (base / "truth7.json").write_text(json.dumps(valley))
    # a finished run's folder and a failed one: what the commands read of them
    report = {"scenario": "smoke", "run_id": "smoke-1", "error": None, "summary": {}}
    for key, error in (("RUN_DIR", None), ("FAILED_RUN", "RuntimeError: the recorder died")):
        (p[key] / "recordings").mkdir(parents=True)
        (p[key] / "report.json").write_text(json.dumps(dict(report, error=error)))
        (p[key] / "report.txt").write_text("a report\n")
    np.savez(base / "demo.npz", states=np.zeros((50, 3)), forces=np.zeros((50, 3)))
    p["DEMO.npz"] = base / "demo.npz"
    # demonstrations with complex states, with states of 1e200, with 10 true labels for 50 samples, sampled at
    # 50 Hz, with a dt of 'x'
    for name, extra in (("COMPLEX", dict(states=np.zeros((50, 3), complex))), ("HUGE", dict(states=np.full((50, 3), 1e200))),
                        ("LABELS", dict(phases=np.zeros(10, int))),
                        ("DT2", dict(dt=0.02)), ("DTX", dict(dt="x"))):
        p[f"{name}.npz"] = base / f"{name.lower()}.npz"
        np.savez(p[f"{name}.npz"], **{"states": np.zeros((50, 3)), "forces": np.zeros((50, 3)), **extra})
    p["ARRAY.npz"] = base / "array.npz"  # one array saved with np.save, named as an archive
    with open(p["ARRAY.npz"], "wb") as f:
        np.save(f, np.zeros((50, 3)))
    # model files: nested past JSON's parser, and the smoke's model with a phase's successor out of range
    p["DEEP.json"] = base / "deep.json"
    p["DEEP.json"].write_text("[" * 100_000 + "]" * 100_000)
    task = json.loads((ROOT / "scenarios" / "models" / "smoke.json").read_text())
    task["metadata"]["impedance"][0]["successor"] = 99
    p["BAD_TASK.json"] = base / "bad_task.json"
    p["BAD_TASK.json"].write_text(json.dumps(task))
    # a reproduction's recording: what etar learn reads of it first is its metadata record
    from services.recordings.writer import EpisodeWriter

    p["REPRO.mcap"] = base / "reproduction_00.mcap"
    with EpisodeWriter(p["REPRO.mcap"], run_id="r1", episode_kind="reproduction", episode_index=0):
        pass
    return p


def with_paths(text: str, paths: dict) -> str:
    for key in sorted(paths, key=len, reverse=True):  # FAILED_RUN before RUN_DIR's RUN
        text = text.replace(key, str(paths[key]))
    return text


def console_script(name: str):
    (entry,) = [e for e in entry_points(group="console_scripts") if e.name == name]
    return entry.load()


@pytest.fixture(scope="module")
def paths(tmp_path_factory):
    return placeholders(tmp_path_factory.mktemp("mistakes"))


@pytest.mark.parametrize("command,code,says", CASES, ids=[c for c, _, _ in CASES])
def test_a_mistake_is_answered_in_one_line(command, code, says, paths, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    program, *argv = shlex.split(with_paths(command, paths))
    try:
        got = console_script(program)(argv)
    except SystemExit as exc:  # argparse's own refusals
        got = exc.code
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert "Traceback" not in captured.err
    assert len(lines) == 1, lines  # refused before any work, so nothing else was said
    assert lines and with_paths(says, paths) in lines[-1], lines
    assert got == code, (got, lines)


def table() -> str:
    rows = ["# Ordinary mistakes and what they are told", "",
            "Every command below is answered in one line on stderr, before any work is done; exit code 2 for a "
            "usage error, 1 for a failed run. FILE, DIR, RUN_DIR and the capitalised file names stand for the "
            "files of each case. Generated from `tests/test_mistakes.py`, which runs every one of them "
            "(`python -m tests.test_mistakes > docs/mistakes.md`).", "",
            "| command | exit | says |", "|---|---|---|"]
    for command, code, says in CASES:
        rows.append(f"| `{command}` | {code} | {says.replace('|', '&#124;')} |")
    return "\n".join(rows) + "\n"


def test_docs_mistakes_md_is_the_table_of_these_cases():
    assert DOC.read_text() == table(), "regenerate: python -m tests.test_mistakes > docs/mistakes.md"


@pytest.mark.parametrize("program", sorted(e.name for e in entry_points(group="console_scripts")
                                           if e.value.startswith("services.cli.")))
def test_every_entry_point_answers_version_on_one_line(program, capsys):
    with pytest.raises(SystemExit) as done:
        console_script(program)(["--version"])
    out, err = capsys.readouterr()
    assert done.value.code == 0 and err == "" and out.count("\n") == 1, (out, err)
    assert out.startswith(f"{program} ") and len(out.split()) >= 2


if __name__ == "__main__":
    sys.stdout.write(table())
