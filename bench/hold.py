"""scenarios/hold.yaml for a benchmark: its stored model named by absolute path, cut to a length."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def hold_scenario(out: Path, seconds: float) -> Path:
    """Write the hold scenario, ``seconds`` long, into ``out``; returns its path."""
    text = (ROOT / "scenarios" / "hold.yaml").read_text()
    text = text.replace("model: models/smoke.json", f"model: {ROOT / 'scenarios' / 'models' / 'smoke.json'}")
    text = text.replace("max_seconds: 60", f"max_seconds: {seconds:g}")
    scenario = out / "hold.yaml"
    scenario.write_text(text)
    return scenario
