"""Scenarios: the inert, validated description of a testbench run, as values.

A scenario says *what* to run (which world, which clock, how many demonstrations from
where, how to learn, how many reproductions and what counts as a success) and nothing
about *how*: nothing here starts a process or touches a simulator.  The YAML file is
parsed into the same constructors the API uses, everything is checked on construction
and every default filled in, so a scenario that loads is a scenario the runner can trust;
``Scenario.replace`` varies one without writing YAML.

- ``checks``: the vocabulary and the checks of single values (``ScenarioError`` names
  the file, the field and the value);
- ``stages``: the demonstrate, learn and reproduce stages and the cell, each field with
  its documentation;
- ``model``: ``Scenario``, its validation, ``replace``, ``to_dict`` and ``to_yaml``;
- ``loading``: a YAML file into a ``Scenario``;
- ``starts``: the starts of the episodes and every seed rule;
- ``reference``: docs/scenarios.md, generated from all of the above.
"""

from services.runtime.cycle import CLOCKS
from services.runtime.roles import RESTARTABLE
from services.scenario.checks import (CRITERIA, FEATURES, MAX_EPISODE_SECONDS, MAX_EPISODES, RESTART_POLICIES,
                                      SELECTIONS, SIDES, STATES, TRANSITIONS, WORLDS, ScenarioError)
from services.scenario.loading import load_scenario
from services.scenario.model import Scenario
from services.scenario.stages import (DEFAULT_STARTS, STAGE_TYPES, VALLEY_GOAL_X, CellSpec, DemonstrateStage,
                                      LearnStage, ReproduceStage, Stage)
from services.scenario.starts import demonstration_starts, reproduction_starts

__all__ = ["CLOCKS", "CRITERIA", "FEATURES", "MAX_EPISODE_SECONDS", "MAX_EPISODES", "RESTART_POLICIES", "RESTARTABLE",
           "SELECTIONS", "SIDES", "STATES", "TRANSITIONS", "WORLDS", "ScenarioError", "load_scenario", "DEFAULT_STARTS",
           "STAGE_TYPES", "VALLEY_GOAL_X", "CellSpec", "DemonstrateStage", "LearnStage", "ReproduceStage", "Scenario",
           "Stage", "demonstration_starts", "reproduction_starts"]
