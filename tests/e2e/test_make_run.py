"""The README's main command as written: ``make run`` from the repository root, in a
fresh process, with a relative output folder that does not exist yet.

The first `make run` on a fresh clone failed while every test passed: the tests all
gave the runner an absolute ``--out``, and only a relative one made the recorder
join the folder twice (out/valley/recordings/out/valley/recordings/...).  So this
test goes through the Makefile itself, on the smoke scenario (``SCENARIO=``, ``OUT=``)."""

import pytest
import json
import os
import subprocess
from pathlib import Path

# whole runs in one process (seconds each): the slow lane
pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]


def make(*args, timeout=900) -> subprocess.CompletedProcess:
    # a fresh process: not a sub-make of `make test` (no MAKEFLAGS, no MAKELEVEL)
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS", "MAKEOVERRIDES")}
    return subprocess.run(["make", *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)


def test_make_run_with_a_relative_output_folder_that_does_not_exist_yet(tmp_path):
    out = tmp_path / "not" / "there" / "yet"
    relative = os.path.relpath(out, ROOT)
    assert not Path(relative).is_absolute() and not out.exists()
    proc = make("run", "SCENARIO=scenarios/smoke.yaml", f"OUT={relative}")
    print(proc.stdout[-3000:], proc.stderr[-3000:])
    assert proc.returncode == 0, proc.stderr[-2000:]

    report = json.loads((out / "report.json").read_text())
    assert report["error"] is None
    # learning read the recordings the demonstrations wrote, where the runner put them
    read = report["learning"]["demonstrations_read"]
    assert [d["path"] for d in read] == ["recordings/demonstration_00.mcap", "recordings/demonstration_01.mcap"]
    assert all(d["samples"] > 100 for d in read)
    assert sorted(p.name for p in (out / "recordings").glob("*.mcap")) == [
        "demonstration_00.mcap", "demonstration_01.mcap", "reproduction_00.mcap"]
    assert not list(out.rglob("not/there/yet")), "a relative folder was joined twice"
    assert (out / "model.json").exists()

    # the last line sums the run up for a newcomer
    last = proc.stdout.strip().splitlines()[-1]
    s = report["summary"]
    assert last.startswith("smoke: 3 phases; ")
    assert f"{s['successes']} of 1 reproductions reached the goal" in last
    assert f"online phase accuracy {s['online_phase_accuracy']:.4f}" in last
    assert last.endswith(f"report {relative}/report.html")
    assert "RUN FAILED" not in last


def test_make_run_exits_non_zero_and_says_why_when_the_run_fails(tmp_path):
    scenario = tmp_path / "broken.yaml"
    scenario.write_text("name: broken\nworld: valley\nstages:\n  - learn: {phases: three}\n")
    proc = make("run", f"SCENARIO={scenario}", f"OUT={tmp_path / 'out'}", timeout=120)
    assert proc.returncode != 0
    assert f"{scenario}: stages[0].learn.phases" in proc.stderr
    assert "Traceback" not in proc.stderr
