"""What the descriptions of a recording and of a run folder share: the error they raise,
a scenario read from its YAML, and how a scenario, the code and a size are written."""

from __future__ import annotations

from pathlib import Path

import yaml

from services.runtime.provenance import describe_code


class InfoError(ValueError):
    """A path ``describe`` cannot describe, naming it and why."""


def scenario_summary(text: str | None, name: str | None) -> dict:
    """Name, seed, world and clock of a scenario's YAML (the attachment, or the run's file)."""
    if text is None:
        return {"attached": False, "name": name, "seed": None}
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        return {"attached": True, "name": name, "seed": None, "problem": f"does not parse: {exc}".splitlines()[0]}
    if not isinstance(data, dict):
        return {"attached": True, "name": name, "seed": None, "problem": "not a mapping"}
    return {"attached": True, "name": data.get("name", name), "seed": data.get("seed"),
            "world": data.get("world"), "clock": data.get("clock")}


def scenario_line(sc: dict) -> str:
    """``scenario_summary`` in one line: name, seed, world and clock, and what is wrong with it."""
    parts = [str(sc.get("name") or "?"), f"seed {sc['seed']}" if sc.get("seed") is not None else "seed ?"]
    extra = ", ".join(f"{k} {sc[k]}" for k in ("world", "clock") if sc.get(k))
    return ", ".join(parts) + (f" ({extra})" if extra else "") + (f" [{sc['problem']}]" if sc.get("problem") else "")


def code_line(code: dict | None) -> str:
    """The code that made a recording or a run (``services.runtime.provenance``), or that none is said."""
    return describe_code(code) if code else "not recorded"


def size_text(n: int | None) -> str:
    """A file's size in bytes, in B, kB, MB or GB."""
    if n is None:
        return "-"
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


def in_run(run_dir: Path, p) -> Path:
    """A path report.json names, resolved: relative to the run's folder unless absolute."""
    p = Path(p)
    return (p if p.is_absolute() else run_dir / p).resolve()
