"""What the figures call the phases and where the run took place: a learned phase by the
true phase the demonstrations matched it to ("phase k = <the labeller's name>",
``robot_sim.labels``), else "phase k"; the run's task world from its scenario."""

from __future__ import annotations

from pathlib import Path

from robot_sim.world.labels import LABELERS
from services.recordings.reader import read_episode


def true_phase_names(world) -> tuple:
    """The labeller's names of the true phases of ``world`` (() for a world without a task)."""
    labeler = LABELERS.get(world) if isinstance(world, str) else None
    return tuple(labeler.names) if labeler is not None else ()


def phase_labels(n_phases: int, phase_to_truth=None, true_names=()) -> list[str]:
    """One legend label per learned phase: "phase k = <true name>" where the mapping
    says which true phase k is and the world names it, else "phase k"."""
    mapping = {int(k): int(v) for k, v in (phase_to_truth or {}).items()}
    labels = []
    for k in range(n_phases):
        v = mapping.get(k)
        labels.append(f"phase {k} = {true_names[v]}" if v is not None and 0 <= v < len(true_names) else f"phase {k}")
    return labels


def true_label(v: int, true_names) -> str:
    """A true phase by its name and number, or its number where the world names none."""
    return f"{true_names[v]} (true phase {v})" if 0 <= v < len(true_names) else f"true phase {v}"


def world_of_scenario(text) -> str | None:
    """The ``world:`` of a scenario's YAML text, None if it has none or does not parse."""
    if not text:
        return None
    import yaml

    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return None
    world = value.get("world") if isinstance(value, dict) else None
    return world if isinstance(world, str) else None


def world_of_run(run_dir: Path, recordings=()) -> str | None:
    """The run's task world: its scenario.yaml's, else the first recording's attached scenario's."""
    try:
        world = world_of_scenario((Path(run_dir) / "scenario.yaml").read_text())
    except OSError:
        world = None
    for path in recordings:
        if world is not None:
            break
        world = world_of_recording(path)
    return world


def world_of_recording(path) -> str | None:
    """The world of the scenario a recording carries, None if it carries none or does not read."""
    try:
        return world_of_scenario(read_episode(path).scenario_text)
    except (OSError, ValueError):
        return None
