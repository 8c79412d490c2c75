"""A full disk: a run fails naming the file and the space left, and leaves what it had
whole and readable; a run's file is whole or absent (services.runtime.files).  On a 1.5 MB
tmpfs mounted here (root and mount needed; skipped with the reason elsewhere), smaller than
the smoke's first demonstration (~2 MB)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from services.runtime.files import FileWriteError, write_file

ROOT = Path(__file__).resolve().parents[2]
SIZE_KB = 1536


@pytest.fixture
def small_disk(tmp_path):
    where = tmp_path / "small"
    where.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={SIZE_KB}k", "tmpfs", str(where)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a {SIZE_KB} kB tmpfs here ({(mounted.stderr or mounted.stdout).strip()}): "
                    "the full-disk tests need root and mount")
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], capture_output=True)


def test_a_file_is_whole_or_absent_on_a_full_disk(small_disk):
    kept = write_file(small_disk / "report.json", '{"kept": true}\n')
    (small_disk / "filler").write_bytes(b"\0" * ((SIZE_KB - 64) * 1024))  # the disk nearly full
    with pytest.raises(FileWriteError) as err:
        write_file(kept, "x" * 2**20)
    said = str(err.value)
    assert said.startswith(f"{kept}: could not be written (No space left on device; ") and " free)" in said, said
    assert "\n" not in said and err.value.errno == 28
    assert kept.read_text() == '{"kept": true}\n'  # as it was
    assert sorted(p.name for p in small_disk.iterdir()) == ["filler", "report.json"]  # no .part left


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["inproc", "zenoh"])
def test_a_run_on_a_full_disk_fails_naming_the_file_and_keeps_what_it_had(small_disk, transport):
    """The smoke scenario into 1.5 MB: its first demonstration fills the disk.  The run exits 1
    without a traceback; each line it says about it names a file and the space left; no
    file is left half written (no 0-byte report, no .part); `etar-bench info` reads the
    folder and names the recording it kept."""
    out = small_disk / "run"
    done = subprocess.run([sys.executable, "-m", "services.cli.bench", "run", "scenarios/smoke.yaml", "--no-figures",
                           "--transport", transport, "--out", str(out)], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    said = done.stderr
    assert done.returncode == 1, said
    assert "Traceback" not in said, said
    last = said.strip().splitlines()[-1]
    assert last.startswith("etar-bench run: failed: ") and "could not be written (No space left on device" in last, last
    assert f"etar-bench info {out}" in last, last
    failed = [line for line in said.splitlines() if line.startswith("run failed:")]
    assert failed and "demonstration_00.mcap: could not be written (No space left on device" in failed[0], said
    files = [p for p in out.rglob("*") if p.is_file()]
    assert not [p for p in files if p.name.endswith(".part") or (p.suffix == ".json" and p.stat().st_size == 0)], files
    if (out / "report.json").exists():
        json.loads((out / "report.json").read_text())
    info = subprocess.run([sys.executable, "-m", "services.cli.bench", "info", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert info.returncode == 1 and "Traceback" not in info.stderr, info.stderr  # 1: a recording incomplete
    assert "recording(s) incomplete or missing" in info.stderr, info.stderr
    assert "recordings/demonstration_00.mcap" in info.stdout and "INCOMPLETE" in info.stdout, info.stdout
