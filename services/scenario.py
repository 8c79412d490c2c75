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

from __future__ import annotations

import dataclasses
import difflib
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any, Union

import numpy as np
import yaml

WORLDS = ("valley", "hose_coupler")
CLOCKS = ("lockstep", "realtime")
RESTART_POLICIES = ("never", "on_failure")
# where a restart mid-run is meaningful: the recorder (a new file, the gap reported) and the
# estimator (its filter re-synchronised); the others hold state a restart would lose (the
# robot's FRI session, the sensor's tare, the commander's and the teacher's episode)
RESTARTABLE = ("recorder", "phase_estimator")
STATES = ("position", "pose")
FEATURES = ("force", "force_torque")
SIDES = ("left", "right")
CRITERIA = ("bic", "aic")
TRANSITIONS = ("effect", "state")
SELECTIONS = ("per_demonstration", "pooled")

# Left-side tcp starts, m.  The valley's is above the left plate, the coupler's above and
# beside the socket (robot_sim.worlds.HoseCoupler.center = (0.55, 0, 0.20)).
DEFAULT_STARTS = {"valley": (0.68, -0.10, 0.40), "hose_coupler": (0.62, -0.08, 0.36)}
VALLEY_GOAL_X = 0.42
# Offsets keep demonstrations, learning and reproductions on independent random streams
# even when every stage inherits the scenario's seed.
DEMONSTRATE_SEED_OFFSET = 1000
REPRODUCE_SEED_OFFSET = 2000
# Per reproduction start: the excluded balls around demonstration starts are a tiny part
# of any sensible perturbation box, so running out of draws means the box is too small.
MAX_START_DRAWS = 1000

Xyz = tuple[float, float, float]

_NOTHING = object()


class ScenarioError(ValueError):
    """A scenario that cannot be used, located by file (and line), field path and value.

    Attributes: ``problem`` (what is expected), ``path`` (e.g. ``stages[1].learn.phases``,
    "" for the whole document), ``value`` (the offending value; ``has_value`` says whether
    there is one), ``source`` (file name or "<dict>"; None when not known) and ``line``.
    """

    def __init__(self, problem: str, *, path: str = "", value: Any = _NOTHING,
                 source: str | None = None, line: int | None = None):
        self.problem = problem
        self.path = path
        self.value = value
        self.source = source
        self.line = line
        super().__init__(self._text())

    @property
    def has_value(self) -> bool:
        return self.value is not _NOTHING

    def _text(self) -> str:
        parts = []
        if self.source is not None:
            parts.append(self.source if self.line is None else f"{self.source}:{self.line}")
        if self.path:
            parts.append(self.path)
        parts.append(f"{self.problem}, got {self.value!r}" if self.has_value else self.problem)
        return ": ".join(parts)

    def within(self, prefix: str = "", source: str | None = None) -> ScenarioError:
        """The same error seen from further out: ``prefix`` goes in front of the path."""
        return ScenarioError(self.problem, path=_join(prefix, self.path), value=self.value,
                             source=self.source if source is None else source, line=self.line)


def _join(prefix: str, path: str) -> str:
    if not prefix:
        return path
    if not path:
        return prefix
    return prefix + path if path.startswith("[") else f"{prefix}.{path}"


# --- value checks: each returns the normalised value or raises with the field's name ----

# what one scenario may ask for, checked before anything starts: a typo such as
# count: 1000000000000 was accepted and grew the runner's memory at 44 MB/s
MAX_EPISODES = 10_000  # per stage
MAX_EPISODE_SECONDS = 3600.0  # simulated, per episode


def _bound_text(minimum: float | None, strict: bool) -> str:
    if minimum is None:
        return ""
    return f" {'>' if strict else '>='} {minimum:g}"


def _is_int(value: Any) -> bool:
    # YAML's true/false are Python ints; a count of `yes` is a typo, not 1.
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _int(value: Any, name: str, minimum: int | None = None, maximum: int | None = None) -> int:
    if not _is_int(value) or (minimum is not None and value < minimum) or (maximum is not None and value > maximum):
        bounds = _bound_text(minimum, False) + (f" and <= {maximum}" if maximum is not None else "")
        raise ScenarioError(f"expected an integer{bounds}", path=name, value=value)
    return int(value)


def _seconds(value: Any, name: str) -> float:
    """An episode's simulated-time limit: > 0 and at most MAX_EPISODE_SECONDS."""
    seconds = _number(value, name, 0.0, strict=True)
    if seconds > MAX_EPISODE_SECONDS:
        raise ScenarioError(f"expected at most {MAX_EPISODE_SECONDS:g} s of simulated time per episode",
                            path=name, value=value)
    return seconds


def _seed(value: Any, name: str) -> int:
    if not _is_int(value) or value < 0:
        raise ScenarioError("expected an integer >= 0 (numpy seeds are non-negative)", path=name, value=value)
    return int(value)


def _number(value: Any, name: str, minimum: float | None = None, strict: bool = False) -> float:
    expected = f"expected a finite number{_bound_text(minimum, strict)}"
    if not isinstance(value, (int, float, np.integer, np.floating)) or isinstance(value, (bool, np.bool_)):
        raise ScenarioError(expected, path=name, value=value)
    x = float(value)
    if not math.isfinite(x) or (minimum is not None and (x <= minimum if strict else x < minimum)):
        raise ScenarioError(expected, path=name, value=value)
    return x


def _choice(value: Any, name: str, options: Sequence[str]) -> str:
    if not isinstance(value, str) or value not in options:
        raise ScenarioError(f"expected one of {', '.join(map(repr, options))}", path=name, value=value)
    return value


def _bool(value: Any, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise ScenarioError("expected true or false", path=name, value=value)
    return bool(value)


def _text(value: Any, name: str, non_empty: bool = False) -> str:
    if not isinstance(value, str) or (non_empty and not value.strip()):
        raise ScenarioError("expected a non-empty string" if non_empty else "expected a string",
                            path=name, value=value)
    return value


def _list(value: Any, name: str, what: str) -> list:
    # A string is a sequence too, and `sides: left` would otherwise read as five sides.
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)):
        raise ScenarioError(f"expected a list of {what}", path=name, value=value)
    return list(value)


def _xyz(value: Any, name: str) -> Xyz:
    items = _list(value, name, "3 numbers [x, y, z] in m")
    if len(items) != 3:
        raise ScenarioError("expected exactly 3 numbers [x, y, z] in m", path=name, value=value)
    x, y, z = (_number(v, f"{name}[{i}]") for i, v in enumerate(items))
    return (x, y, z)


def _sides(value: Any, name: str) -> tuple[str, ...]:
    items = _list(value, name, "sides (left, right)")
    if not items:
        raise ScenarioError("expected at least one side (left, right)", path=name, value=value)
    return tuple(_choice(v, f"{name}[{i}]", SIDES) for i, v in enumerate(items))


def _transitions(value: Any, name: str) -> tuple[str, ...]:
    """One transition model or a list of distinct ones (``[effect, state]``: ETAR and STAR)."""
    items = [value] if isinstance(value, str) else _list(value, name, "transition models")
    if not items:
        raise ScenarioError(f"expected one of {', '.join(TRANSITIONS)} or a list of them", path=name, value=value)
    for i, item in enumerate(items):
        _choice(item, f"{name}[{i}]" if not isinstance(value, str) else name, TRANSITIONS)
    if len(set(items)) != len(items):
        raise ScenarioError("a transition model is listed twice", path=name, value=list(items))
    return tuple(items)


def _phases(value: Any, name: str) -> int | str:
    if isinstance(value, str) and value == "auto":
        return value
    if not _is_int(value) or value < 1:
        raise ScenarioError("expected 'auto' or an integer >= 1", path=name, value=value)
    return int(value)


def _candidates(value: Any, name: str) -> tuple[int, ...]:
    items = _list(value, name, "phase counts (integers >= 1)")
    if not items:
        raise ScenarioError("expected at least one phase count", path=name, value=value)
    counts = tuple(_int(v, f"{name}[{i}]", 1) for i, v in enumerate(items))
    if len(set(counts)) != len(counts):
        raise ScenarioError("expected distinct phase counts", path=name, value=value)
    return counts


def _set(obj: Any, name: str, value: Any) -> None:
    # Normalising inside __post_init__ of a frozen dataclass (lists to tuples, ints to
    # floats) is the one place the objects are written after creation.
    object.__setattr__(obj, name, value)


def _mirror(xyz: Xyz, side: str) -> Xyz:
    """The start on ``side`` of a left-side start: the task is mirror-symmetric in y."""
    x, y, z = xyz
    return (x, -y, z) if side == "right" else (x, y, z)


# --- stages ------------------------------------------------------------------------------

class _MotionStage:
    """What demonstrate and reproduce share: sides, a start, a goal, a seed."""

    def _spread(self) -> float:
        raise NotImplementedError

    def _for_world(self, world: str, default_seed: int):
        """This stage with the world's defaults filled in, checked against the world."""
        if world == "hose_coupler":
            if self.sides != ("left",):
                raise ScenarioError("the hose_coupler world has one side: omit sides or use [left]",
                                    path="sides", value=list(self.sides))
            if self.goal_x is not None:
                raise ScenarioError("applies to the valley world only: omit it",
                                    path="goal_x", value=self.goal_x)
            goal_x = None
        else:
            goal_x = VALLEY_GOAL_X if self.goal_x is None else self.goal_x
        start = DEFAULT_STARTS[world] if self.start is None else self.start
        if world == "valley":
            spread = self._spread()
            if start[1] + spread >= 0.0:
                raise ScenarioError(
                    f"the valley's left side is y < 0: a left start must stay there with its "
                    f"+-{spread:g} m spread (the right side mirrors it)", path="start", value=list(start))
            if goal_x >= start[0] - spread:
                raise ScenarioError(
                    f"goal_x must lie below every start's x (the teacher slides towards -x; "
                    f"starts reach down to x = {start[0] - spread:g})", path="goal_x", value=goal_x)
        seed = default_seed if self.seed is None else self.seed
        return dataclasses.replace(self, start=start, goal_x=goal_x, seed=seed)


@dataclass(frozen=True)
class DemonstrateStage(_MotionStage):
    """Record ``count`` kinesthetic demonstrations by the simulated teacher.

    ``start`` is the left-side tcp start (m, base frame); demonstration i starts on
    ``sides[i % len(sides)]`` (the right side mirrors y) plus a uniform offset of up to
    ``start_spread`` per axis.  ``None`` for start, goal_x and seed means "the
    scenario's default", which `Scenario` fills in.
    """

    count: int
    sides: tuple[str, ...] = ("left",)
    start: Xyz | None = None
    start_spread: float = 0.01
    goal_x: float | None = None
    max_seconds: float = 40.0
    seed: int | None = None

    @property
    def kind(self) -> str:
        return "demonstrate"

    def __post_init__(self):
        _set(self, "count", _int(self.count, "count", 1, MAX_EPISODES))
        _set(self, "sides", _sides(self.sides, "sides"))
        if self.start is not None:
            _set(self, "start", _xyz(self.start, "start"))
        _set(self, "start_spread", _number(self.start_spread, "start_spread", 0.0))
        if self.goal_x is not None:
            _set(self, "goal_x", _number(self.goal_x, "goal_x"))
        _set(self, "max_seconds", _seconds(self.max_seconds, "max_seconds"))
        if self.seed is not None:
            _set(self, "seed", _seed(self.seed, "seed"))

    def _spread(self) -> float:
        return self.start_spread


@dataclass(frozen=True)
class LearnStage:
    """Fit ETAR (or STAR) to every demonstration recorded before this stage.

    With ``phases == 'auto'`` each of ``candidates`` is fitted and ``criterion`` picks
    one; with a fixed ``phases`` the candidates are not used (see `phase_counts`).

    ``transitions``: ``effect`` (ETAR), ``state`` (STAR) or a list of both.  With a list
    the first is the run's model (``model.json``; it alone chooses the number of
    phases); each further one is fitted with that number of phases on the same
    demonstrations (``model-STAR.json``), and every one is scored against the true
    phases (thesis 6.3), so a reproduce stage can run the same starts with each.
    """

    phases: int | str = "auto"
    candidates: tuple[int, ...] = (1, 2, 3, 4, 5, 6)
    criterion: str = "bic"
    selection: str = "per_demonstration"
    transitions: str | tuple[str, ...] = ("effect",)
    restarts: int = 4
    max_iter: int = 200
    seed: int | None = None

    @property
    def kind(self) -> str:
        return "learn"

    @property
    def phase_counts(self) -> tuple[int, ...]:
        """The numbers of phases to fit: the candidates with 'auto', else just ``phases``."""
        return self.candidates if self.phases == "auto" else (self.phases,)

    def __post_init__(self):
        _set(self, "phases", _phases(self.phases, "phases"))
        _set(self, "candidates", _candidates(self.candidates, "candidates"))
        _set(self, "criterion", _choice(self.criterion, "criterion", CRITERIA))
        _set(self, "selection", _choice(self.selection, "selection", SELECTIONS))
        _set(self, "transitions", _transitions(self.transitions, "transitions"))
        _set(self, "restarts", _int(self.restarts, "restarts", 1))
        _set(self, "max_iter", _int(self.max_iter, "max_iter", 1))
        if self.seed is not None:
            _set(self, "seed", _seed(self.seed, "seed"))

    def _for_world(self, world: str, default_seed: int) -> LearnStage:
        return self if self.seed is not None else dataclasses.replace(self, seed=default_seed)


@dataclass(frozen=True)
class ReproduceStage(_MotionStage):
    """Run the learned model online ``count`` times, from starts no demonstration used.

    Reproduction i starts on ``sides[i % len(sides)]`` at the (mirrored) nominal
    ``start`` plus a uniform offset within +-``start_perturbation`` per axis, redrawn
    while closer than ``min_distance_from_demonstrations`` to a demonstration start of
    that side.  It succeeds when it ends within ``goal_tolerance`` of the goal, inside
    ``max_seconds`` and without a contact force above ``max_contact_force``.
    ``transitions`` (default: the run's model): with a list, every start is reproduced
    once with the model of each listed transition model, which the learn stage must
    have learned (``[effect, state]``: the same starts driven by ETAR and by STAR).
    """

    count: int
    sides: tuple[str, ...] = ("left",)
    start: Xyz | None = None
    start_perturbation: float = 0.03
    min_distance_from_demonstrations: float = 0.005
    goal_x: float | None = None
    goal_tolerance: float = 0.01
    max_contact_force: float = 60.0
    max_seconds: float = 40.0
    stop_at_goal: bool = True
    transitions: str | tuple[str, ...] | None = None
    seed: int | None = None

    @property
    def kind(self) -> str:
        return "reproduce"

    def __post_init__(self):
        _set(self, "count", _int(self.count, "count", 1, MAX_EPISODES))
        _set(self, "sides", _sides(self.sides, "sides"))
        if self.start is not None:
            _set(self, "start", _xyz(self.start, "start"))
        _set(self, "start_perturbation", _number(self.start_perturbation, "start_perturbation", 0.0))
        _set(self, "min_distance_from_demonstrations",
             _number(self.min_distance_from_demonstrations, "min_distance_from_demonstrations", 0.0))
        if self.goal_x is not None:
            _set(self, "goal_x", _number(self.goal_x, "goal_x"))
        _set(self, "goal_tolerance", _number(self.goal_tolerance, "goal_tolerance", 0.0, strict=True))
        _set(self, "max_contact_force", _number(self.max_contact_force, "max_contact_force", 0.0, strict=True))
        _set(self, "max_seconds", _seconds(self.max_seconds, "max_seconds"))
        _set(self, "stop_at_goal", _bool(self.stop_at_goal, "stop_at_goal"))
        if self.transitions is not None:
            _set(self, "transitions", _transitions(self.transitions, "transitions"))
        if self.seed is not None:
            _set(self, "seed", _seed(self.seed, "seed"))

    def _spread(self) -> float:
        return self.start_perturbation


@dataclass(frozen=True)
class CellSpec:
    """The simulated cell's parameters a study may vary (``etar-bench sweep``)."""

    sensor_noise: float = 1.0  # ATI white noise, as a multiple of the Mini45's
    plate_friction: float = 0.25  # valley: sliding friction coefficient of the plates
    fri_packet_loss: float = 0.0  # probability that a command packet is lost on the FRI link
    fri_delay_ms: float = 0.0  # every command packet arrives this much later, ms
    fri_jitter_ms: float = 0.0  # and a further uniform 0..this, ms
    fri_corruption: float = 0.0  # probability that a command packet arrives damaged
    fri_duplication: float = 0.0  # probability that a command packet arrives twice
    fri_reordering: float = 0.0  # probability that a command packet arrives after the next cycle's
    fri_faults_from_s: float = 0.0  # the link faults act from this many seconds into each episode
    fri_faults_until_s: float = math.inf  # ... until this many

    def __post_init__(self):
        _set(self, "sensor_noise", _number(self.sensor_noise, "sensor_noise", 0.0))
        _set(self, "plate_friction", _number(self.plate_friction, "plate_friction", 0.0, strict=True))
        for name in ("fri_packet_loss", "fri_corruption", "fri_duplication", "fri_reordering"):
            p = _number(getattr(self, name), name, 0.0)
            if p > 1.0:
                raise ScenarioError("expected a probability in [0, 1]", path=name, value=getattr(self, name))
            _set(self, name, p)
        for name in ("fri_delay_ms", "fri_jitter_ms"):
            ms = _number(getattr(self, name), name, 0.0)
            if ms > 1000.0:
                raise ScenarioError("expected at most 1000 ms", path=name, value=getattr(self, name))
            _set(self, name, ms)
        _set(self, "fri_faults_from_s", _number(self.fri_faults_from_s, "fri_faults_from_s", 0.0))
        until = self.fri_faults_until_s
        if not (isinstance(until, (int, float)) and not isinstance(until, bool) and until > self.fri_faults_from_s):
            raise ScenarioError(f"expected a number of seconds > fri_faults_from_s ({self.fri_faults_from_s})",
                                path="fri_faults_until_s", value=until)
        _set(self, "fri_faults_until_s", float(until))


Stage = Union[DemonstrateStage, LearnStage, ReproduceStage]
STAGE_TYPES: dict[str, type] = {"demonstrate": DemonstrateStage, "learn": LearnStage, "reproduce": ReproduceStage}


def _check_stage_order(kinds: list[str], has_model: bool = False) -> None:
    demonstrations = learned = reproduced = 0
    order = "the order is demonstrate..., learn, reproduce..."
    for i, kind in enumerate(kinds):
        problem = None
        if kind == "learn" and has_model:
            problem = "a scenario with a model file does not learn: remove the learn stage or the model key"
        elif kind == "demonstrate" and (learned or reproduced):
            problem = f"a demonstrate stage must come before the learn and reproduce stages ({order})"
        elif kind == "learn" and learned:
            problem = f"only one learn stage is allowed ({order})"
        elif kind == "learn" and reproduced:
            problem = f"the learn stage must come before the reproduce stages ({order})"
        elif kind == "learn" and not demonstrations:
            problem = f"a learn stage needs a demonstrate stage before it ({order})"
        elif kind == "reproduce" and not learned and not has_model:
            problem = f"a reproduce stage needs a learn stage before it ({order})"
        if problem:
            raise ScenarioError(problem, path=f"stages[{i}]", value=kinds)
        demonstrations += kind == "demonstrate"
        learned += kind == "learn"
        reproduced += kind == "reproduce"


# --- the scenario ------------------------------------------------------------------------

@dataclass(frozen=True, kw_only=True)
class Scenario:
    """A whole run: the world, the clock, the seeds and the stages, defaults filled in.

    ``source`` names where the description came from (a file name, or "<dict>"); it is
    used in error messages and is not part of `to_dict`.
    """

    name: str
    description: str = ""
    world: str
    clock: str = "lockstep"
    seed: int = 0
    state: str = "position"
    features: str = "force"
    model: str | None = None
    cell: CellSpec = CellSpec()
    restart: Any = ()  # {role: policy} in YAML; stored as sorted (role, policy) pairs
    stages: tuple[Stage, ...]
    source: str = "<dict>"

    def __post_init__(self):
        _set(self, "source", str(self.source))
        try:
            self._validate()
        except ScenarioError as err:
            raise err.within(source=self.source) from None

    def _validate(self) -> None:
        _text(self.name, "name", non_empty=True)
        _text(self.description, "description")
        _choice(self.world, "world", WORLDS)
        _choice(self.clock, "clock", CLOCKS)
        _set(self, "seed", _seed(self.seed, "seed"))
        _choice(self.state, "state", STATES)
        _choice(self.features, "features", FEATURES)
        if self.model is not None:
            _text(self.model, "model", non_empty=True)
        if not isinstance(self.cell, CellSpec):
            raise ScenarioError("expected a CellSpec", path="cell", value=self.cell)
        if self.world != "valley" and self.cell.plate_friction != CellSpec.plate_friction:
            raise ScenarioError("applies to the valley world only: omit it", path="cell.plate_friction",
                                value=self.cell.plate_friction)
        _set(self, "restart", _restart(self.restart))
        stages = _list(self.stages, "stages", "stages")
        if not stages:
            raise ScenarioError("expected at least one stage", path="stages", value=self.stages)
        for i, stage in enumerate(stages):
            if not isinstance(stage, tuple(STAGE_TYPES.values())):
                raise ScenarioError("expected a DemonstrateStage, LearnStage or ReproduceStage",
                                    path=f"stages[{i}]", value=stage)
        _check_stage_order([stage.kind for stage in stages], self.model is not None)
        learned = next((s.transitions for s in stages if s.kind == "learn"), ())
        for i, stage in enumerate(stages):
            if stage.kind == "reproduce" and stage.transitions is not None:
                missing = [t for t in stage.transitions if t not in learned]
                if missing:
                    raise ScenarioError(
                        f"the learn stage learns {list(learned) or 'nothing (the model file is used)'}, not "
                        f"{missing}: reproduce with the models learned here, or add them to learn.transitions",
                        path=f"stages[{i}].reproduce.transitions", value=list(stage.transitions))
        resolved = []
        ordinal = {kind: 0 for kind in STAGE_TYPES}
        for i, stage in enumerate(stages):
            offset = {"demonstrate": DEMONSTRATE_SEED_OFFSET, "learn": 0,
                      "reproduce": REPRODUCE_SEED_OFFSET}[stage.kind]
            # Two demonstrate stages that both inherit the seed must not replay each other.
            default_seed = self.seed + offset + ordinal[stage.kind]
            ordinal[stage.kind] += 1
            try:
                resolved.append(stage._for_world(self.world, default_seed))
            except ScenarioError as err:
                raise err.within(f"stages[{i}].{stage.kind}") from None
        _set(self, "stages", tuple(resolved))

    @property
    def demonstrate_stages(self) -> tuple[DemonstrateStage, ...]:
        return tuple(s for s in self.stages if s.kind == "demonstrate")

    @property
    def learn_stage(self) -> LearnStage | None:
        return next((s for s in self.stages if s.kind == "learn"), None)

    @property
    def reproduce_stages(self) -> tuple[ReproduceStage, ...]:
        return tuple(s for s in self.stages if s.kind == "reproduce")

    def model_path(self) -> Path | None:
        """The model file as an absolute path; a relative ``model`` is taken from the
        scenario file's directory (from the working directory for a scenario that came
        from a dict)."""
        if self.model is None:
            return None
        path = Path(self.model).expanduser()
        if not path.is_absolute():
            source = Path(self.source)
            path = (source.parent / path) if source.is_file() else path
        return path.resolve()  # absolute: it is handed to other processes

    def with_clock(self, clock: str) -> Scenario:
        """A copy run on another clock: the same scenario, lockstep for CI, realtime for the lab."""
        return dataclasses.replace(self, clock=clock)

    @classmethod
    def from_dict(cls, data: Any, source: str | PathLike = "<dict>") -> Scenario:
        """Parse plain data (as from YAML) into a Scenario; ScenarioError names ``source``."""
        source = str(source)
        if not isinstance(data, Mapping):
            raise ScenarioError("expected a mapping of scenario fields at the top level",
                                value=data, source=source)
        fields = _construct_args(cls, data, "", source, exclude={"source"})
        fields["stages"] = _parse_stages(data["stages"], source)
        if "cell" in fields:
            fields["cell"] = _parse_cell(fields["cell"], source)
        return cls(**fields, source=source)

    def to_dict(self) -> dict[str, Any]:
        """Plain data (lists, not tuples) that `from_dict` turns back into an equal Scenario."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
               if f.name not in ("stages", "source")}
        if self.model is None:
            del out["model"]
        if not self.restart:
            del out["restart"]
        else:
            out["restart"] = dict(self.restart)
        if self.cell == CellSpec():
            del out["cell"]
        else:
            out["cell"] = dataclasses.asdict(self.cell)
        out["stages"] = [{stage.kind: _stage_dict(stage)} for stage in self.stages]
        return out


def _stage_dict(stage: Stage) -> dict[str, Any]:
    out = {}
    for f in dataclasses.fields(stage):
        value = getattr(stage, f.name)
        if value is not None:  # None only where the world forbids the key (goal_x off the valley)
            out[f.name] = list(value) if isinstance(value, tuple) else value
    return out


def _construct_args(cls: type, data: Mapping, path: str, source: str, exclude=frozenset()) -> dict:
    """Check ``data``'s keys against ``cls``'s fields: unknown keys and missing required ones."""
    known = [f.name for f in dataclasses.fields(cls) if f.init and f.name not in exclude]
    for key in data:
        if key not in known:
            close = difflib.get_close_matches(str(key), known, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ScenarioError(f"unknown key ({hint}known keys: {', '.join(known)})",
                                path=_join(path, str(key)), value=key, source=source)
    for f in dataclasses.fields(cls):
        required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        if f.name in known and required and f.name not in data:
            raise ScenarioError("required field is missing", path=_join(path, f.name), source=source)
    return dict(data)


def _restart(value: Any) -> tuple:
    items = value.items() if isinstance(value, Mapping) else value
    try:
        pairs = [(role, policy) for role, policy in items]
    except (TypeError, ValueError):
        raise ScenarioError("expected a mapping of role: policy (e.g. recorder: on_failure)", path="restart",
                            value=value) from None
    for role, policy in pairs:
        if role not in RESTARTABLE:
            raise ScenarioError(f"a restart is meaningful for {' and '.join(RESTARTABLE)} only (the others "
                                "hold state a restart would lose: the FRI session, the tare, the episode)",
                                path=f"restart.{role}", value=role)
        _choice(policy, f"restart.{role}", RESTART_POLICIES)
    return tuple(sorted(pairs))


def _parse_cell(value: Any, source: str) -> CellSpec:
    if value is None:
        return CellSpec()
    if not isinstance(value, Mapping):
        raise ScenarioError("expected a mapping of cell parameters", path="cell", value=value, source=source)
    args = _construct_args(CellSpec, value, "cell", source)
    try:
        return CellSpec(**args)
    except ScenarioError as err:
        raise err.within("cell", source) from None


def _parse_stages(value: Any, source: str) -> tuple[Stage, ...]:
    if not isinstance(value, (list, tuple)) or not value:
        raise ScenarioError("expected a non-empty list of stages (demonstrate, learn, reproduce)",
                            path="stages", value=value, source=source)
    return tuple(_parse_stage(item, i, source) for i, item in enumerate(value))


def _parse_stage(item: Any, index: int, source: str) -> Stage:
    path = f"stages[{index}]"
    kinds = ", ".join(STAGE_TYPES)
    if not isinstance(item, Mapping) or len(item) != 1:
        raise ScenarioError(f"expected a mapping with exactly one key, the stage kind ({kinds})",
                            path=path, value=item, source=source)
    ((kind, params),) = item.items()
    if kind not in STAGE_TYPES:
        raise ScenarioError(f"unknown stage kind (expected one of {kinds})", path=path, value=kind, source=source)
    cls = STAGE_TYPES[kind]
    path = f"{path}.{kind}"
    if params is None:  # `- learn:` with nothing under it: all defaults
        params = {}
    if not isinstance(params, Mapping):
        raise ScenarioError("expected a mapping of stage fields", path=path, value=params, source=source)
    args = _construct_args(cls, params, path, source)
    try:
        return cls(**args)
    except ScenarioError as err:
        raise err.within(path, source) from None


# --- files -------------------------------------------------------------------------------

class _Loader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys and reads 1e-3 as a float.

    PyYAML keeps the last of two equal keys silently (a pasted `count:` overrides the
    first) and, following YAML 1.1, reads exponent floats without a dot as strings.
    """

    def construct_mapping(self, node, deep=False):
        first_line: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                if key in first_line:
                    raise yaml.constructor.ConstructorError(
                        "while constructing a mapping", node.start_mark,
                        f"duplicate key {key!r} (first on line {first_line[key]})", key_node.start_mark)
                first_line[key] = key_node.start_mark.line + 1
            except TypeError:  # unhashable key: SafeLoader reports it
                continue
        return super().construct_mapping(node, deep=deep)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                  |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                  |[-+]?\.(?:inf|Inf|INF)
                  |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


def load_scenario(path: str | PathLike) -> Scenario:
    """Read and validate a scenario file; every problem is a ScenarioError naming the file."""
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise ScenarioError(f"cannot read the file ({err})", source=source) from err
    try:
        data = yaml.load(text, Loader=_Loader)
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        problem = err.problem or err.context or "invalid YAML"
        column = f" (column {mark.column + 1})" if mark is not None else ""
        # An unclosed bracket is noticed lines later: say where the construct began.
        began = ""
        if err.problem and err.context and err.context_mark is not None and mark is not None \
                and err.context_mark.line != mark.line:
            began = f", {err.context} on line {err.context_mark.line + 1}"
        raise ScenarioError(f"invalid YAML: {problem}{column}{began}", source=source,
                            line=mark.line + 1 if mark is not None else None) from None
    except yaml.YAMLError as err:
        raise ScenarioError(f"invalid YAML: {err}", source=source) from None
    if data is None:
        raise ScenarioError("the file is empty: expected a scenario mapping (name, world, stages)", source=source)
    return Scenario.from_dict(data, source=source)


# --- start positions ---------------------------------------------------------------------

def _side_of(stage: DemonstrateStage | ReproduceStage, i: int) -> str:
    return stage.sides[i % len(stage.sides)]


def demonstration_starts(stage: DemonstrateStage, world: str, seed: int) -> list[tuple[str, Xyz]]:
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


def reproduction_starts(stage: ReproduceStage, world: str, seed: int,
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
