"""Writing a run's files (reports, models, tables, figures): each whole or absent.

Every such file is written to a hidden ``.NAME.part`` beside it and renamed into place,
so a full disk, a read-only folder or a signal leaves the file as it was (or absent),
never half written; a reader (``etar-bench info``, ``report``, a foreign tool) never
sees a 0-byte report.  A failure raises :class:`FileWriteError`, one line that names the
file, the system's reason and the space left on its file system.

Recordings are the exception: they are streamed as they are recorded, so that a recorder
killed mid-episode leaves its complete chunks (``etar-bench recover``).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path


class FileWriteError(OSError):
    """A run's file that could not be written: the message names it and the space left
    (``errno`` and ``filename`` are the failure's, as OSError has them)."""

    def __init__(self, message: str, errno: int | None = None, filename: str | None = None):
        super().__init__(message)
        self.message, self.errno, self.filename = message, errno, filename

    def __str__(self) -> str:
        return self.message


def free_space(path) -> str:
    """The space left on the file system that holds ``path`` (or its nearest existing folder)."""
    p = Path(path)
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        free = shutil.disk_usage(p).free
    except OSError:
        return "free space unknown"
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if free >= size:
            return f"{free / size:.1f} {unit} free"
    return f"{free} B free"


def write_error(path, exc: OSError) -> FileWriteError:
    """``exc`` (raised writing ``path``) as one line naming the file and the space left."""
    return FileWriteError(f"{path}: could not be written ({exc.strerror or exc}; {free_space(path)})", exc.errno,
                          str(path))


def write_via(path, write: Callable[[Path], object]) -> Path:
    """``write(tmp)`` writes the file at a temporary path beside ``path``, which then takes
    its place.  FileWriteError (nothing left behind, ``path`` as it was) if it cannot."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.part")
    try:
        write(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise write_error(path, exc) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_file(path, data: str | bytes) -> Path:
    """``data`` (text as UTF-8) as the whole of ``path`` (``write_via``)."""
    raw = data.encode("utf-8") if isinstance(data, str) else bytes(data)

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            f.write(raw)
            f.flush()
            os.fsync(f.fileno())
    return write_via(path, write)
