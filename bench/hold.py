"""scenarios/hold.yaml for a benchmark, cut to a length."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def hold_scenario(seconds: float):
    """The hold scenario (the smoke reproduction held at its goal with the stored model,
    realtime), ``seconds`` long, as a scenario value."""
    from services.scenario import load_scenario

    return load_scenario(ROOT / "scenarios" / "hold.yaml").replace("reproduce.max_seconds", seconds)
