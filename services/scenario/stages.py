"""A scenario's stages (demonstrate, learn, reproduce) and its cell, each a frozen value
validated on construction; every field carries its documentation (``doc``), from which
the scenario reference (docs/scenarios.md) is generated."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Union

from robot_sim.cycle import FRI_CYCLE_NS
from robot_sim.krc.faults import LinkFaultError, LinkFaultSpec
from robot_sim.world.tasks import HoseCoupler, Valley
from services.runtime.messages import ESTIMATOR_PERIOD_NS, SAMPLE_RATE_HZ
from services.scenario.checks import (CRITERIA, MAX_EM_ITERATIONS, MAX_EPISODE_SECONDS, MAX_EPISODES, MAX_PHASES,
                                      MAX_PHYSICS_SUBSTEPS, MAX_RESTARTS, SELECTIONS, ScenarioError, Xyz, _bool,
                                      _candidates, _choice, _int, _number, _phases, _seconds, _seed, _set, _sides,
                                      _transitions, _xyz)
from services.scenario.starts import DEMONSTRATE_SEED_OFFSET, REPRODUCE_SEED_OFFSET

def doc(text: str, default: Any = dataclasses.MISSING) -> Any:
    """A field with its documentation (the scenario reference, docs/scenarios.md, is made of it)."""
    return dataclasses.field(default=default, metadata={"doc": text})


# the learner's samples are the estimator's (100 Hz): a demonstration must hold two of them
MIN_DEMONSTRATION_SECONDS = 2 * ESTIMATOR_PERIOD_NS / 1e9
FRI_PREFIX = "fri_"  # the cell's keys for the FRI link's faults (robot_sim.krc.faults.LinkFaultSpec)
DEFAULT_STARTS = {"valley": Valley.start_left, "hose_coupler": HoseCoupler.start_left}
VALLEY_GOAL_X = Valley.goal_x


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

    count: int = doc(f'how many demonstrations, 1..{MAX_EPISODES}')
    sides: tuple[str, ...] = doc('left | right, cycled over the demonstrations (valley; the hose coupler has one side: omit or [left])', ("left",))
    start: Xyz | None = doc("[x, y, z] tcp start for the LEFT side, m, base frame (the right side mirrors y); default: the world's (see the world defaults)", None)
    start_spread: float = doc('m >= 0: a uniform random offset per axis', 0.01)
    goal_x: float | None = doc("valley only: the teacher stops sliding at this x (below every start's x); default the valley's", None)
    max_seconds: float = doc(f'simulated-time limit per demonstration, s, >= {MIN_DEMONSTRATION_SECONDS:g} and <= '
                             f'{MAX_EPISODE_SECONDS:g}', 40.0)
    seed: int | None = doc(f"int >= 0; default the scenario's seed + {DEMONSTRATE_SEED_OFFSET} (+ j for the j-th "
                           "demonstrate stage)", None)

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
        if self.max_seconds < MIN_DEMONSTRATION_SECONDS:
            raise ScenarioError(f"a demonstration is recorded at {SAMPLE_RATE_HZ:g} Hz for the learner: expected at "
                                f"least {MIN_DEMONSTRATION_SECONDS:g} s (two samples)", path="max_seconds",
                                value=self.max_seconds)
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

    phases: int | str = doc(f"'auto' (chosen by the criterion among the candidates) or a number of phases, "
                            f"1..{MAX_PHASES} (the thesis' tasks need at most 6)", "auto")
    candidates: tuple[int, ...] = doc(f'distinct phase counts, 1..{MAX_PHASES}, tried with phases: auto',
                                      (1, 2, 3, 4, 5, 6))
    criterion: str = doc('bic | aic', "bic")
    selection: str = doc('per_demonstration (each demonstration chooses, the majority wins: thesis 6.1) | pooled (one score over all demonstrations)', "per_demonstration")
    transitions: str | tuple[str, ...] = doc("effect (ETAR) | state (STAR), or a list of both: the first is the run's model and alone chooses the number of phases, each further one is fitted with that number and every one is scored against the true phases", ("effect",))
    restarts: int = doc(f'EM restarts, 1..{MAX_RESTARTS} (the best is kept)', 4)
    max_iter: int = doc(f'EM iterations per restart, 1..{MAX_EM_ITERATIONS}', 200)
    seed: int | None = doc("int >= 0; default the scenario's seed", None)

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
        _set(self, "restarts", _int(self.restarts, "restarts", 1, MAX_RESTARTS))
        _set(self, "max_iter", _int(self.max_iter, "max_iter", 1, MAX_EM_ITERATIONS))
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

    count: int = doc(f'how many starts, 1..{MAX_EPISODES}')
    sides: tuple[str, ...] = doc('as in demonstrate', ("left",))
    start: Xyz | None = doc('nominal start for the LEFT side, m; default as in demonstrate', None)
    start_perturbation: float = doc('m >= 0: each start is drawn uniformly within +- this per axis of the nominal one', 0.03)
    min_distance_from_demonstrations: float = doc('m >= 0: a start closer than this to a demonstration start of its side is drawn again', 0.005)
    goal_x: float | None = doc('valley only, as in demonstrate', None)
    goal_tolerance: float = doc('m > 0: a reproduction ending within this of the goal reached it', 0.01)
    max_contact_force: float = doc('N > 0: a reproduction whose peak contact force exceeds this fails', 60.0)
    max_seconds: float = doc(f'simulated-time limit per reproduction, s, > 0 and <= {MAX_EPISODE_SECONDS:g}', 40.0)
    stop_at_goal: bool = doc('true: an episode ends at the goal; false: it runs the whole max_seconds, holding at the goal (load and timing runs)', True)
    transitions: str | tuple[str, ...] | None = doc("default the run's model; a list (e.g. [effect, state]): every start is reproduced once with each listed model, which the learn stage must have learned", None)
    seed: int | None = doc(f"int >= 0; default the scenario's seed + {REPRODUCE_SEED_OFFSET} (+ j for the j-th "
                           "reproduce stage)", None)

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
    """The simulated cell's parameters a study may vary (``etar-bench sweep``).  In a
    scenario the FRI link's faults are keys of the cell's own, ``fri_<field>`` for each
    field of ``robot_sim.krc.faults.LinkFaultSpec`` (``fri_packet_loss``, ``fri_delay_ms``, ...)."""

    sensor_noise: float = doc(">= 0: the ATI's white noise as a multiple of the Mini45's", 1.0)
    plate_friction: float = doc("> 0, valley only: the plates' sliding friction coefficient", Valley.friction)
    physics_substeps: int = doc("physics steps per 1 ms FRI cycle, the KRC's law in each: 1 as shipped, 10 for "
                                "the finer reference physics (docs/contact.md; a divisor of 1 000 000, at most 100)",
                                1)
    fri: LinkFaultSpec = LinkFaultSpec()  # the FRI link's faults

    def __post_init__(self):
        _set(self, "sensor_noise", _number(self.sensor_noise, "sensor_noise", 0.0))
        _set(self, "plate_friction", _number(self.plate_friction, "plate_friction", 0.0, strict=True))
        _set(self, "physics_substeps", _int(self.physics_substeps, "physics_substeps", 1, MAX_PHYSICS_SUBSTEPS))
        if FRI_CYCLE_NS % self.physics_substeps:
            raise ScenarioError(f"expected a divisor of the {FRI_CYCLE_NS} ns FRI cycle (1, 2, 4, 5, 10, 20, ...)",
                                path="physics_substeps", value=self.physics_substeps)
        if not isinstance(self.fri, LinkFaultSpec):
            raise ScenarioError("expected a LinkFaultSpec", path="fri", value=self.fri)

    @classmethod
    def keys(cls) -> list[str]:
        """The keys of ``cell`` in a scenario."""
        return ["sensor_noise", "plate_friction", "physics_substeps",
                *(FRI_PREFIX + f.name for f in dataclasses.fields(LinkFaultSpec))]

    @classmethod
    def from_keys(cls, data: Mapping) -> CellSpec:
        """The cell of a scenario's ``cell`` mapping; a ScenarioError names the key."""
        faults = {k[len(FRI_PREFIX):]: v for k, v in data.items() if k.startswith(FRI_PREFIX)}
        try:
            fri = LinkFaultSpec(**faults)
        except LinkFaultError as err:
            raise ScenarioError(err.problem, path=FRI_PREFIX + err.field, value=err.value) from None
        return cls(**{k: v for k, v in data.items() if not k.startswith(FRI_PREFIX)}, fri=fri)

    def to_keys(self) -> dict[str, Any]:
        out = {"sensor_noise": self.sensor_noise, "plate_friction": self.plate_friction,
               "physics_substeps": self.physics_substeps}
        out.update({FRI_PREFIX + f.name: getattr(self.fri, f.name) for f in dataclasses.fields(LinkFaultSpec)})
        return out


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


