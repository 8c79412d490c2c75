"""One demonstration by the simulated teacher, run by the nodes in one process (the same
nodes, the same episode protocol as every run): what ``etar-bench demo`` records, and how
the tests look at the teacher in the task worlds."""

from __future__ import annotations

from pathlib import Path

from services.scenario import Scenario

MAX_SECONDS = 60.0  # a demonstration's simulated-time limit unless told otherwise


def demonstration_scenario(world: str = "valley", *, side: str = "left", seed: int = 0, spread: float = 0.0,
                           max_seconds: float = MAX_SECONDS, start=None, goal_x: float | None = None) -> Scenario:
    """A scenario of one demonstration.  ``start``: the left-side tcp start (the right side
    mirrors it; default the world's), ``spread``: a uniform offset per axis, m; ``goal_x``:
    where the valley's teacher stops (default the world's).  A ScenarioError names what
    the world does not allow (the hose coupler has one side)."""
    stage = dict(count=1, sides=[side], start_spread=spread, max_seconds=max_seconds)
    if start is not None:
        stage["start"] = list(start)
    if goal_x is not None:
        stage["goal_x"] = goal_x
    return Scenario.from_dict(dict(name=f"demonstration_{world}", world=world, seed=seed,
                                   stages=[{"demonstrate": stage}]), source="a demonstration")


def record_demonstration(scenario: Scenario, out, progress=print, replace: bool = False) -> tuple[dict, Path]:
    """``scenario`` run in one process into ``out``: (its report, the demonstration's recording)."""
    from services.run.options import RunOptions  # the runner on use: the CLI reads this module's defaults
    from services.run.runner import Runner

    report = Runner(scenario, RunOptions(out=str(out), transport="inproc", figures=False, replace=replace),
                    progress).run()
    (demonstration,) = report["demonstrations"]
    return report, Path(out).resolve() / demonstration["path"]
