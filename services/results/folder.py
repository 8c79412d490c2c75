"""A run's folder: what a run leaves in it, and the rule that one folder holds one run.

A run never writes over another: an ``--out`` that already holds a run is refused
unless the run is asked to replace it, and then everything the earlier run left is
removed first, so that no report, recording or figure of it can be taken for this
run's (report.html embeds every figure it finds)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np

from services.ros2 import BAGS_DIR

SCENARIO_FILE = "scenario.yaml"  # the scenario as run, every default filled in
# everything a run, `etar-bench figures`, `etar-bench compare` and `etar-bench export --rosbag2`
# (its default folder) write into the folder
RUN_PRODUCTS = ("report.json", "report.txt", "report.html", "report.html.error", "timing.txt", "timing.png",
                "timing.png.error", "figures", "figures.error", "figures.skipped", "recordings", "logs",
                "model.json", "model-ETAR.json", "model-STAR.json", SCENARIO_FILE, "comparison.txt",
                "comparison.json", BAGS_DIR)
# the files that say a folder holds a run
RUN_MARKERS = ("report.json", SCENARIO_FILE, "recordings", "model.json")
# what a sweep writes into its --out (services.run.sweep; one folder holds one sweep, as one holds one run),
# the first the file that says a folder holds a sweep
SWEEP_PRODUCTS = ("sweep.json", "table.csv", "table.json", "comparison.txt", "scenarios", "runs")
SWEEP_FILE = SWEEP_PRODUCTS[0]


def kept_recordings(run_dir) -> bool:
    """Whether a run kept its recordings: one without a recordings/ folder kept none by choice
    (a sweep's ``--record summary``), and what reads it reads its report alone; a recording
    missing from a recordings/ folder is lost."""
    return (Path(run_dir) / "recordings").exists()


def holds_a_run(folder: Path) -> bool:
    return any((folder / name).exists() for name in RUN_MARKERS)


def _sweep_of(folder: Path) -> Path | None:
    """The sweep's folder that ``folder`` is, or is a part of (its runs, its scenarios); else None."""
    if (folder / SWEEP_FILE).exists():
        return folder
    if folder.name in SWEEP_PRODUCTS and (folder.parent / SWEEP_FILE).exists():
        return folder.parent
    return None


def check_run_folder(folder: Path, flag_value, *, replace: bool) -> bool:
    """Whether ``folder`` holds a run that ``prepare_run_folder`` would remove (``replace``);
    a ValueError naming ``--out`` if it cannot take a new run.  Changes nothing."""
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"--out {flag_value}: {folder} is a file; --out names the run's folder")
    sweep = _sweep_of(folder)
    if sweep is not None:  # --replace removes a run, never a sweep or a part of one
        raise ValueError(f"--out {flag_value}: {folder} is {'a' if sweep == folder else 'part of a'} sweep's "
                         f"folder ({sweep / SWEEP_FILE}); choose a folder of the run's own")
    if not folder.exists() or not holds_a_run(folder):
        return False
    if not replace:
        raise ValueError(f"--out {flag_value}: {folder} already holds a run; choose another folder, or "
                         "--replace to remove that run first")
    return True


def prepare_run_folder(folder: Path, flag_value, *, replace: bool) -> None:
    """Make sure ``folder`` can take a new run, or raise a ValueError naming ``--out``."""
    if not check_run_folder(folder, flag_value, replace=replace):
        return
    for name in RUN_PRODUCTS:
        path = folder / name
        try:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            elif path.exists() or path.is_symlink():
                path.unlink()
        except OSError as exc:
            raise ValueError(f"--out {flag_value}: cannot remove the earlier run's {path} "
                             f"({exc.strerror or exc})") from None


class RunFolderError(ValueError):
    """A folder that is not a finished run's, or its report.json unreadable: names the file."""


def read_report(run_dir, *, required: bool = True) -> dict:
    """A run's report.json (``{}`` when there is none and ``required`` is False).  NaN, which
    reports written before they were strict JSON could hold, is read as None."""
    run_dir = Path(run_dir)
    path = run_dir / "report.json"
    if not path.is_file():
        if not required:
            return {}
        raise RunFolderError(f"{path}: missing (is {run_dir} a finished run's folder?)")
    try:
        report = json.loads(path.read_bytes(), parse_constant=lambda name: None)
    except (OSError, ValueError) as exc:  # UnicodeDecodeError is a ValueError
        raise RunFolderError(f"{path}: not a JSON report ({type(exc).__name__}: {exc})") from None
    if not isinstance(report, dict):
        raise RunFolderError(f"{path}: not a run report (a JSON {type(report).__name__}, not an object)")
    return report


def report_episodes(report: dict, kind: str, path) -> list:
    """The report's episodes of ``kind`` ('demonstrations', 'reproductions', 'served'; none
    when it has none): a list, or RunFolderError naming the file (``path``) and the field."""
    episodes = report.get(kind) or []
    if not isinstance(episodes, list):
        raise RunFolderError(f"{path}: {kind}: expected a list of episodes, got {type(episodes).__name__}")
    return episodes


def strict_json(value):
    """``value`` as strict JSON can hold it (report.json, ``--json``): numpy scalars as
    Python numbers, paths as strings, tuples as lists, NaN and infinities as None (JSON has
    no NaN; a reader must not meet one)."""
    if isinstance(value, dict):
        return {str(k): strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
