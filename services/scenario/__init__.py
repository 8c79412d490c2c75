"""Scenarios: the inert, validated description of a testbench run.

A scenario says *what* to run — which world, which clock, how many
demonstrations from where, how to learn, how many reproductions and what counts
as a success — and nothing about *how*: this module never starts a process or
touches a simulator.  The runner consumes a `Scenario`.  Everything is checked
when the objects are constructed (``DemonstrateStage(count=0)`` raises), and the
YAML file is parsed into those same constructors, so a scenario that loads is a
scenario the runner can trust.  All the defaults are filled in on construction:
the runner reads values, never ``None``.

Schema (every key optional unless marked required; unknown keys are errors)::

    name: valley                      # str, required
    description: "..."                # str, default ""
    world: valley                     # valley | hose_coupler, required
    clock: lockstep                   # lockstep | realtime, default lockstep
    seed: 0                           # int >= 0, default 0: base seed
    state: position                   # position | pose: what ETAR uses as its state, default position
    features: force                   # force | force_torque: ETAR transition/effect features, default force
    model: models/smoke.json          # a model file learned earlier (relative to this file), default none:
                                      #   the reproductions use it instead of a learn stage
    restart:                          # per service, what the runner does if it dies mid-run (optional):
      recorder: on_failure            #   never (default: the run fails) | on_failure (started again: a
      phase_estimator: on_failure     #   recorder writes on in a new file and the report names the gap,
                                      #   an estimator re-synchronises its filter); these two roles only
    cell:                             # the simulated cell's physics and devices (all optional)
      sensor_noise: 1.0               # ATI white noise as a multiple of the Mini45's, >= 0, default 1
      plate_friction: 0.25            # valley only: sliding friction coefficient of the plates, > 0
      fri_packet_loss: 0.0            # probability that a command packet is lost on the FRI link, [0, 1]
      fri_delay_ms: 0.0               # FRI link fault: every command packet arrives this much later, 0..1000 ms
      fri_jitter_ms: 0.0              # and a further uniform 0..this, 0..1000 ms
      fri_corruption: 0.0             # probability that a command packet arrives damaged, [0, 1]
      fri_duplication: 0.0            # probability that a command packet arrives twice, [0, 1]
      fri_reordering: 0.0             # probability that a command packet is held back 1.5 ms and so arrives
                                      #   after the next cycle's, [0, 1]
      fri_faults_from_s: 0.0          # the FRI faults above act from this many s into each episode, >= 0
      fri_faults_until_s: .inf        # ... until this many s into it (> from; default: to the episode's end)
    stages:                           # required, non-empty list; each item has exactly one key
      - demonstrate:
          count: 6                    # int, 1..10000, required
          sides: [left]               # left | right, cycled over the demonstrations; valley only
                                      #   (default [left]); hose_coupler: omit or [left]
          start: [0.68, -0.10, 0.40]  # tcp start for the LEFT side, m (the right side mirrors y);
                                      #   default valley [0.68, -0.10, 0.40], hose_coupler [0.62, -0.08, 0.36]
          start_spread: 0.01          # m >= 0: uniform random offset per axis, default 0.01
          goal_x: 0.42                # valley only: the teacher stops sliding at this x, default 0.42
          max_seconds: 40             # > 0, <= 3600: simulated-time limit per demonstration, default 40
          seed: 10                    # int >= 0, default: scenario seed + 1000 (+ j for the j-th demonstrate stage)
      - learn:
          phases: auto                # 'auto' or int >= 1, default auto
          candidates: [1, 2, 3, 4, 5, 6]   # distinct ints >= 1, tried with auto, default 1..6
          criterion: bic              # bic | aic, default bic
          selection: per_demonstration  # per_demonstration (each demonstration chooses, the majority
                                      # wins: thesis 6.1) | pooled (one score over all), default per_demonstration
          transitions: effect         # effect (ETAR) | state (STAR), default effect
          restarts: 4                 # int >= 1, default 4
          max_iter: 200               # int >= 1, default 200
          seed: 0                     # int >= 0, default: scenario seed
      - reproduce:
          count: 20                   # int, 1..10000, required
          sides: [left]               # as in demonstrate
          start: [0.68, -0.10, 0.40]  # nominal start (left side), default as in demonstrate
          start_perturbation: 0.03    # m >= 0: starts drawn uniformly within +- this per axis, default 0.03
          min_distance_from_demonstrations: 0.005  # m >= 0: redraw a start closer than this to any
                                      #   demonstration start of its side, default 0.005
          goal_x: 0.42                # valley only, default 0.42
          goal_tolerance: 0.01        # m > 0, default 0.01
          max_contact_force: 60.0     # N > 0: a reproduction whose peak contact force exceeds this fails
          max_seconds: 40             # > 0, <= 3600, default 40
          stop_at_goal: true          # bool, default true; false: run the whole max_seconds, holding at
                                      #   the goal (load and timing runs)
          seed: 20                    # int >= 0, default: scenario seed + 2000 (+ j for the j-th reproduce stage)

Rules: the stages run in the order demonstrate*, learn?, reproduce*; a learn
stage needs a demonstrate stage before it and a reproduce stage needs the learn
stage before it, or a ``model`` file (then there is no learn stage).  Numbers
must be finite; ``start`` has exactly 3 numbers; in
the valley the left side is y < 0, so a left start (with its spread or
perturbation) must stay at y < 0, and ``goal_x`` must lie below the start's x
(the teacher slides towards -x).  Seeds are non-negative because numpy's
generators reject negative seeds.

Errors are `ScenarioError` (a ValueError) naming the file, the field path and
the value, e.g. ``scenarios/x.yaml: stages[1].learn.phases: expected 'auto' or
an integer >= 1, got 'three'``; YAML syntax errors name the file and line.

Start positions are part of the description, not of the execution: they follow
from the stage and a seed alone (`demonstration_starts`, `reproduction_starts`),
so a run can be replayed and a report can say where each episode began.
"""

from services.runtime.cycle import CLOCKS
from services.runtime.roles import RESTARTABLE
from services.scenario.checks import (CRITERIA, FEATURES, MAX_EPISODE_SECONDS, MAX_EPISODES, RESTART_POLICIES,
                                      SELECTIONS, SIDES, STATES, TRANSITIONS, WORLDS, ScenarioError)
from services.scenario.loading import load_scenario
from services.scenario.model import (DEFAULT_STARTS, STAGE_TYPES, VALLEY_GOAL_X, CellSpec, DemonstrateStage,
                                     LearnStage, ReproduceStage, Scenario, Stage)
from services.scenario.starts import demonstration_starts, reproduction_starts

__all__ = ["CLOCKS", "CRITERIA", "FEATURES", "MAX_EPISODE_SECONDS", "MAX_EPISODES", "RESTART_POLICIES", "RESTARTABLE",
           "SELECTIONS", "SIDES", "STATES", "TRANSITIONS", "WORLDS", "ScenarioError", "load_scenario", "DEFAULT_STARTS",
           "STAGE_TYPES", "VALLEY_GOAL_X", "CellSpec", "DemonstrateStage", "LearnStage", "ReproduceStage", "Scenario",
           "Stage", "demonstration_starts", "reproduction_starts"]
