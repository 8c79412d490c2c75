"""What a recording or a run folder holds, at a glance (``etar-bench info PATH [--json]``).

``describe(path)`` returns plain data (strict JSON: no NaN, no numpy) and
``info_text(d)`` the same for people: a recording's (``recording``) or a run folder's
(``run_folder``).

Errors: a path that does not exist, a folder that holds no run, an unreadable
report.json raise ``InfoError``; a file that is not MCAP or a damaged recording raise
``RecordingError`` (``read_episode``'s); both are ValueErrors whose one-line message
names the file.
"""

from __future__ import annotations

from pathlib import Path

from services.results.info.common import InfoError
from services.results.info.recording import describe_recording, recording_text
from services.results.info.run_folder import describe_run, run_scenario, run_text

__all__ = ["InfoError", "describe", "describe_recording", "describe_run", "info_text", "run_scenario"]


def describe(path) -> dict:
    """A recording (a file) or a run folder (a folder, or its report.json) as plain data."""
    p = Path(path)
    if not p.exists():
        raise InfoError(f"{p}: no such file or folder")
    if p.is_dir():
        return describe_run(p)
    if p.name == "report.json":
        return describe_run(p.parent)
    return describe_recording(p)


def info_text(d: dict) -> str:
    """``describe``'s data for people."""
    return run_text(d) if d.get("kind") == "run" else recording_text(d)
