"""What made a run: the code (version, git commit, uncommitted changes), when, by which
command line, on which versions of the libraries that decide its numbers.  A report
and a recording carry it so that a result can be traced back and made again."""

from __future__ import annotations

import datetime
import functools
import shlex
import subprocess
import sys
from importlib import metadata
from pathlib import Path

PACKAGE = "etar-testbench"
# the distributions whose versions can change a run's numbers or its files
DEPENDENCIES = ("numpy", "scipy", "numba", "mujoco", "pin", "eclipse-zenoh", "mcap", "filterpy", "pyyaml",
                "matplotlib")
SOURCE_ROOT = Path(__file__).resolve().parents[2]  # the checkout holding services/, when it is one


def _version(distribution: str) -> str | None:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return None


def _git(root: Path, *args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def code(root: Path | None = None) -> dict:
    """{"version", "commit", "dirty"}: the package's version and, when it runs from a git
    checkout (``root``, default the one holding this code), the commit and whether a
    tracked file differs from it (None: not a checkout; untracked files change nothing
    the program runs).  Asked once per process for the default checkout."""
    return dict(_code(SOURCE_ROOT if root is None else Path(root)))


@functools.cache
def _code(root: Path) -> tuple:
    # an installed copy inside some other repository is not that repository's checkout
    commit = _git(root, "rev-parse", "HEAD") if (root / ".git").exists() else None
    dirty = None
    if commit is not None:
        status = _git(root, "status", "--porcelain", "--untracked-files=no")
        dirty = None if status is None else bool(status)
    return (("version", _version(PACKAGE) or "unknown"), ("commit", commit), ("dirty", dirty))


def code_text(root: Path | None = None) -> str:
    """One line: ``0.1.0 (git 1a2b3c4, uncommitted changes)``."""
    return describe_code(code(root))


def describe_code(c: dict) -> str:
    """``code()``'s dict (or the part of a report's provenance it made) as one line."""
    commit = c.get("commit")
    if not commit:
        return str(c.get("version"))
    return f"{c.get('version')} (git {commit[:7]}{', uncommitted changes' if c.get('dirty') else ''})"


def provenance(command: str | None = None) -> dict:
    """The code, the date (UTC), the command (default: this process's command line), the
    Python and the main dependencies' versions."""
    if command is None:
        argv = sys.argv
        command = shlex.join([Path(argv[0]).name, *argv[1:]]) if argv and argv[0] else ""
    return {**code(), "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "command": command,
            "python": sys.version.split()[0],
            "dependencies": {name: _version(name) for name in DEPENDENCIES}}
