"""The kernel cache step make runs after installing: its flags, and the model it runs with."""

import subprocess
import sys
from pathlib import Path

from services.run import kernel_cache

ROOT = Path(__file__).resolve().parents[3]


def test_a_bad_flag_is_one_line_and_exit_2_and_help_says_what_it_does():
    bad = subprocess.run([sys.executable, "-m", "services.run.kernel_cache", "--fast"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.strip().splitlines() == [
        "python -m services.run.kernel_cache: error: --fast: not a flag of this program (see --help)"], bad.stderr
    assert bad.stdout == ""
    part = subprocess.run([sys.executable, "-m", "services.run.kernel_cache", "--part", "all"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert part.returncode == 2 and part.stderr.strip().splitlines() == [
        "python -m services.run.kernel_cache: error: --part all: not one of nodes, learning"], part.stderr
    shown = subprocess.run([sys.executable, "-m", "services.run.kernel_cache", "--help"], cwd=ROOT,
                           capture_output=True, text=True, timeout=60)
    assert shown.returncode == 0 and "compiled into its cache once" in shown.stdout and "--part" not in shown.stdout


def test_the_nodes_part_runs_the_checkouts_smoke_model_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert kernel_cache._smoke_model() == ROOT / "scenarios" / "models" / "smoke.json"


def test_ctrl_c_while_compiling_is_one_line_and_exit_130():
    """Ctrl-C reaches the step and both of its processes (a terminal signals the group)."""
    import os
    import signal

    from tests.support import popen_as_from_a_terminal

    proc = popen_as_from_a_terminal([sys.executable, "-m", "services.run.kernel_cache"], cwd=ROOT,
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                    start_new_session=True)
    try:
        assert proc.stdout.readline().startswith("compiling numba's kernels")  # its two processes are starting
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, (proc.returncode, out, err)
    assert err.strip().splitlines() == [
        "kernel cache: interrupted; the kernels not compiled yet compile on first use"], err
