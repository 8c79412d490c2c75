"""Where each episode starts and which seed drives it: functions of the stage and a seed
alone, so a run can be replayed and a report can say where each episode began."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from services.scenario.checks import (MAX_START_DRAWS, SIDES, WORLDS, ScenarioError, Xyz, _choice, _seed,
                                      _xyz)



class EpisodeStage(Protocol):
    """What the starts read of a demonstrate or reproduce stage (``services.scenario.stages``,
    which imports this module for its seeds)."""

    count: int
    sides: tuple[str, ...]
    start: Xyz

    def _for_world(self, world: str, seed: int) -> EpisodeStage: ...

# Offsets keep demonstrations, learning and reproductions on independent random streams
# even when every stage inherits the scenario's seed.
DEMONSTRATE_SEED_OFFSET = 1000
REPRODUCE_SEED_OFFSET = 2000


TEACHER_SEED_STRIDE = 1000  # the teacher's seeds of one stage: stage seed x this + i


def teacher_seed(stage_seed: int, i: int) -> int:
    """The seed of the teacher's hand in the i-th demonstration of a stage."""
    return stage_seed * TEACHER_SEED_STRIDE + i


def _mirror(xyz: Xyz, side: str) -> Xyz:
    """The start on ``side`` of a left-side start: the task is mirror-symmetric in y."""
    x, y, z = xyz
    return (x, -y, z) if side == "right" else (x, y, z)


def _side_of(stage: EpisodeStage, i: int) -> str:
    return stage.sides[i % len(stage.sides)]


def demonstration_starts(stage: EpisodeStage, world: str, seed: int) -> list[tuple[str, Xyz]]:
    """The (side, tcp start in m) of each demonstration of ``stage``, a function of ``seed``.

    Demonstration i starts at ``stage.start`` mirrored onto ``sides[i % len(sides)]``,
    plus a uniform offset in [-start_spread, start_spread] per axis.
    """
    world = _choice(world, "world", WORLDS)
    seed = _seed(seed, "seed")
    stage = stage._for_world(world, seed)
    rng = np.random.default_rng(seed)
    starts = []
    for i in range(stage.count):
        side = _side_of(stage, i)
        xyz = np.array(_mirror(stage.start, side)) + rng.uniform(-stage.start_spread, stage.start_spread, 3)
        starts.append((side, tuple(float(v) for v in xyz)))
    return starts


def reproduction_starts(stage: EpisodeStage, world: str, seed: int,
                        demonstration_starts: Sequence[tuple[str, Sequence[float]]]) -> list[tuple[str, Xyz]]:
    """The (side, tcp start in m) of each reproduction of ``stage``, a function of ``seed``.

    Reproduction i starts at ``stage.start`` mirrored onto ``sides[i % len(sides)]``,
    plus a uniform offset in [-start_perturbation, start_perturbation] per axis, redrawn
    while it is closer than ``min_distance_from_demonstrations`` to any of the
    ``demonstration_starts`` on the same side: a reproduction is meant to start where
    no demonstration did.  After MAX_START_DRAWS failed draws the perturbation box is
    too small for that distance, which is a ScenarioError.
    """
    world = _choice(world, "world", WORLDS)
    seed = _seed(seed, "seed")
    stage = stage._for_world(world, seed)
    by_side: dict[str, list] = {side: [] for side in SIDES}
    for i, (side, xyz) in enumerate(demonstration_starts):
        by_side[_choice(side, f"demonstration_starts[{i}]", SIDES)].append(_xyz(xyz, f"demonstration_starts[{i}]"))
    avoid = {side: np.array(points, dtype=np.float64).reshape(-1, 3) for side, points in by_side.items()}
    reach, min_distance = stage.start_perturbation, stage.min_distance_from_demonstrations
    rng = np.random.default_rng(seed)
    starts = []
    for i in range(stage.count):
        side = _side_of(stage, i)
        nominal = np.array(_mirror(stage.start, side))
        for _ in range(MAX_START_DRAWS):
            xyz = nominal + rng.uniform(-reach, reach, 3)
            others = avoid[side]
            if others.shape[0] == 0 or np.linalg.norm(others - xyz, axis=1).min() >= min_distance:
                break
        else:
            raise ScenarioError(
                f"reproduction {i} ({side} side): in {MAX_START_DRAWS} draws no start within "
                f"+-{reach:g} m of {[round(v, 4) for v in nominal.tolist()]} was at least "
                f"{min_distance:g} m from every demonstration start; the perturbation is too small "
                f"(raise start_perturbation or lower min_distance_from_demonstrations)",
                path="start_perturbation", value=reach)
        starts.append((side, tuple(float(v) for v in xyz)))
    return starts
