"""What a run would otherwise find out only once its services are up: that the
scenario's model file exists, loads and fits the scenario, and that every episode's
start is one the arm can reach with the tool pointing down, above the floor.  A
scenario that passes here fails, if at all, for reasons the run is meant to measure.

``preflight(scenario)`` raises a ScenarioError naming the field and the value; the runner
calls it before anything starts, and its stages run the starts it drew; ``etar-bench
check`` calls it without running."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from etar.task import LearnedTask, TaskError, load_task
from robot_sim.world.labels import LABELERS
from services.scenario import Scenario, ScenarioError, demonstration_starts, reproduction_starts

FLOOR_Z = 0.0  # the floor plane of every task world (robot_sim.world.tasks), m
EPISODE_NAMES = {"demonstrate": "demonstration", "reproduce": "reproduction"}  # by stage kind


@dataclass(frozen=True)
class Preflight:
    """What the checks found: the scenario's stored model (None when it learns one) and
    every episode's start, stage by stage, in the order the runner walks them."""

    model: LearnedTask | None
    starts: tuple  # (stage index, kind, episode within the stage, side, (x, y, z) m)

    def stage_starts(self, index: int) -> list:
        """(side, (x, y, z) m) of each episode of stage ``index``, in the order it runs them."""
        return [(side, xyz) for i, _, _, side, xyz in self.starts if i == index]


def preflight(scenario: Scenario) -> Preflight:
    task = _stored_model(scenario) if scenario.model is not None else None
    starts = _starts(scenario)
    _reachable(scenario, starts)
    return Preflight(task, tuple(starts))


def _stored_model(scenario: Scenario) -> LearnedTask:
    path = scenario.model_path()
    if not path.is_file():
        raise ScenarioError("the model file does not exist" if not path.exists() else "the model is not a file",
                            path="model", value=str(path), source=scenario.source)
    try:
        task = load_task(path)
    except TaskError as exc:
        raise ScenarioError(f"the model file does not load ({exc})", path="model", value=str(path),
                            source=scenario.source) from None
    if task.state != scenario.state or task.features != scenario.features:
        raise ScenarioError(f"the model sees {task.state}/{task.features}, the scenario "
                            f"{scenario.state}/{scenario.features} (state/features)", path="model",
                            value=str(path), source=scenario.source)
    if task.state_resolution != scenario.state_resolution:
        raise ScenarioError(f"the model was learned on a state rounded to {task.state_resolution:g} m, the scenario "
                            f"asks for {scenario.state_resolution:g} m (state_resolution)", path="model",
                            value=str(path), source=scenario.source)
    labeler = LABELERS.get(scenario.world)
    # which true phase each learned one is: the reproductions are scored by it (a phase the
    # world does not have scores every estimate wrong, as a model of another world would)
    unknown = [] if labeler is None else sorted((k, v) for k, v in (task.phase_to_truth or {}).items()
                                                if v >= len(labeler.names))
    if unknown:
        k, v = unknown[0]
        raise ScenarioError(f"the model matches its phase {k} to true phase {v}; the {scenario.world} world's true "
                            f"phases are 0..{len(labeler.names) - 1} ({', '.join(labeler.names)}) "
                            f"(metadata.phase_to_truth)", path="model", value=str(path), source=scenario.source)
    return task


def _starts(scenario: Scenario) -> list:
    """Every episode's start, drawn once (the stages run these)."""
    out, demos = [], []
    for i, stage in enumerate(scenario.stages):
        if stage.kind == "demonstrate":
            drawn = demonstration_starts(stage, scenario.world, stage.seed)
            demos += drawn
        elif stage.kind == "reproduce":
            try:
                drawn = reproduction_starts(stage, scenario.world, stage.seed, demos)
            except ScenarioError as exc:
                raise exc.within(f"stages[{i}].reproduce", source=scenario.source) from None
        else:
            continue
        out += [(i, stage.kind, j, side, xyz) for j, (side, xyz) in enumerate(drawn)]
    return out


def _reachable(scenario: Scenario, starts: list) -> None:
    if not starts:
        return
    from robot_sim.arm.kinematics import ArmKinematics

    kinematics = ArmKinematics()
    for i, kind, j, side, xyz in starts:
        problem = start_problem(xyz, kinematics)
        if problem:
            raise ScenarioError(f"{EPISODE_NAMES[kind]} {j + 1} ({side} side) would start at {problem}",
                                path=f"stages[{i}].{kind}.start", value=[round(v, 4) for v in xyz],
                                source=scenario.source)


def start_problem(xyz, kinematics=None) -> str | None:
    """Why the tcp cannot start at ``xyz`` (m) with the tool pointing down, or None."""
    import pinocchio as pin

    from robot_sim.arm.kinematics import ArmKinematics, READY
    from robot_sim.world.teacher import DOWN

    if xyz[2] <= FLOOR_Z:
        return f"z = {xyz[2]:.3f} m, at or below the floor (z = {FLOOR_Z:g} m): raise the start's z"
    try:
        (kinematics or ArmKinematics()).inverse_kinematics(pin.SE3(DOWN, np.asarray(xyz, dtype=np.float64)), READY)
    except ValueError:
        reach = float(np.linalg.norm(np.asarray(xyz)))
        return (f"a point the arm cannot reach with the tool pointing down ({reach:.2f} m from its base; the "
                f"LWR4+ reaches about 0.8 m)")
    return None
