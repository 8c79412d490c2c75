"""The scenario as a value: ``Scenario`` and its stages, validated on construction."""

from __future__ import annotations

import dataclasses
import difflib
import re
from collections.abc import Mapping
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any, Union

import yaml

from robot_sim.fri import LinkFaultError, LinkFaultSpec
from robot_sim.worlds import HoseCoupler, Valley

from services.runtime.cycle import CLOCKS
from services.runtime.roles import RESTARTABLE
from services.scenario.checks import (CRITERIA, FEATURES, MAX_EPISODES, RESTART_POLICIES,
                                      SELECTIONS, STATES, WORLDS, ScenarioError, Xyz, _bool, _candidates, _choice,
                                      _int, _join, _list, _number, _phases, _seconds, _seed, _set, _sides, _text,
                                      _transitions, _xyz)
from services.scenario.starts import DEMONSTRATE_SEED_OFFSET, REPRODUCE_SEED_OFFSET

FRI_PREFIX = "fri_"  # the cell's keys for the FRI link's faults (robot_sim.fri.LinkFaultSpec)
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
    """The simulated cell's parameters a study may vary (``etar-bench sweep``).  In a
    scenario the FRI link's faults are keys of the cell's own, ``fri_<field>`` for each
    field of ``robot_sim.fri.LinkFaultSpec`` (``fri_packet_loss``, ``fri_delay_ms``, ...)."""

    sensor_noise: float = 1.0  # ATI white noise, as a multiple of the Mini45's
    plate_friction: float = Valley.friction  # valley: sliding friction coefficient of the plates
    fri: LinkFaultSpec = LinkFaultSpec()  # the FRI link's faults

    def __post_init__(self):
        _set(self, "sensor_noise", _number(self.sensor_noise, "sensor_noise", 0.0))
        _set(self, "plate_friction", _number(self.plate_friction, "plate_friction", 0.0, strict=True))
        if not isinstance(self.fri, LinkFaultSpec):
            raise ScenarioError("expected a LinkFaultSpec", path="fri", value=self.fri)

    @classmethod
    def keys(cls) -> list[str]:
        """The keys of ``cell`` in a scenario."""
        return ["sensor_noise", "plate_friction", *(FRI_PREFIX + f.name for f in dataclasses.fields(LinkFaultSpec))]

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
        out = {"sensor_noise": self.sensor_noise, "plate_friction": self.plate_friction}
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
    # the stages as described, before the world's and the seed's defaults were filled in:
    # what `replace` varies, so that a new seed reaches every stage that inherits it
    _described: tuple = dataclasses.field(default=(), init=False, repr=False, compare=False)

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
        _set(self, "_described", tuple(stages))
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
    def roles(self) -> tuple[str, ...]:
        """The services the stages need: the cell always, the teacher to demonstrate, the
        estimator and the commander to reproduce (a run may add the live view's bridge)."""
        kinds = {s.kind for s in self.stages}
        return (("robot", "ft_sensor", "recorder") + (("teacher",) if "demonstrate" in kinds else ())
                + (("phase_estimator", "impedance_commander") if "reproduce" in kinds else ()))

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
        return self.replace("clock", clock)

    def replace(self, path: str, value: Any) -> Scenario:
        """This scenario with one field set, validated as any scenario (a ScenarioError names
        ``path``).  ``path`` is a top-level key (``seed``, ``clock``), ``cell.KEY``, or
        ``STAGE.KEY`` for every stage of that kind (``reproduce.count``), ``STAGE[i].KEY``
        for the i-th (``reproduce[1].start_perturbation``).  Defaults stay defaults: a new
        ``seed`` reaches every stage that inherits it, as if the file had said it."""
        data = self.described()
        try:
            _assign(data, path, value)
            return Scenario.from_dict(data, source=self.source)
        except ScenarioError as err:
            raise ScenarioError(err.problem, path=err.path, value=err.value,
                                source=f"{self.source} with {path} = {value!r}") from None

    def described(self) -> dict[str, Any]:
        """Plain data of the scenario as described: the stages' defaults not filled in."""
        out = self.to_dict()
        out["stages"] = [{stage.kind: _stage_dict(stage)} for stage in self._described]
        return out

    def to_yaml(self) -> str:
        """The scenario as run, as YAML that `load_scenario` reads back into an equal
        scenario; the model is named by its absolute path, so the text stands on its own
        (what every recording attaches)."""
        data = self.to_dict()
        if self.model is not None:
            data["model"] = str(self.model_path())
        return yaml.safe_dump(data, sort_keys=False, default_flow_style=None)

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
               if f.init and f.name not in ("stages", "source")}
        if self.model is None:
            del out["model"]
        if not self.restart:
            del out["restart"]
        else:
            out["restart"] = dict(self.restart)
        if self.cell == CellSpec():
            del out["cell"]
        else:
            out["cell"] = self.cell.to_keys()
        out["stages"] = [{stage.kind: _stage_dict(stage)} for stage in self.stages]
        return out


_STAGE_PATH = re.compile(r"^(?P<kind>[a-z]+)(\[(?P<index>\d+)\])?$")


def _assign(data: dict, path: str, value: Any) -> None:
    """Set ``path`` (see `Scenario.replace`) in the plain data ``data``."""
    def refuse(problem: str):
        raise ScenarioError(problem, path=path, value=value)

    head, _, rest = path.partition(".")
    if not head:
        refuse("expected a field path such as seed, cell.sensor_noise or reproduce.count")
    if not rest:
        data[head] = value
        return
    if head == "cell":
        if "." in rest:
            refuse("cell has no nested keys")
        data["cell"] = dict(data.get("cell") or {}, **{rest: value})
        return
    m = _STAGE_PATH.match(head)
    if m is None or m["kind"] not in STAGE_TYPES or "." in rest:
        refuse(f"expected a top-level key, cell.KEY or STAGE.KEY with STAGE one of {', '.join(STAGE_TYPES)} "
               "(optionally STAGE[i])")
    stages = [s for s in data["stages"] if m["kind"] in s]
    if not stages:
        refuse(f"the scenario has no {m['kind']} stage")
    if m["index"] is not None:
        i = int(m["index"])
        if i >= len(stages):
            refuse(f"the scenario has {len(stages)} {m['kind']} stage(s)")
        stages = [stages[i]]
    for stage in stages:
        stage[m["kind"]] = dict(stage[m["kind"]] or {}, **{rest: value})


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
    required = [f.name for f in dataclasses.fields(cls) if f.name in known and f.default is dataclasses.MISSING
                and f.default_factory is dataclasses.MISSING]
    _check_keys(known, required, data, path, source)
    return dict(data)


def _check_keys(known: list, required: list, data: Mapping, path: str, source: str) -> None:
    """Unknown keys (with the nearest known one) and missing required ones."""
    for key in data:
        if key not in known:
            close = difflib.get_close_matches(str(key), known, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ScenarioError(f"unknown key ({hint}known keys: {', '.join(known)})",
                                path=_join(path, str(key)), value=key, source=source)
    for name in required:
        if name not in data:
            raise ScenarioError("required field is missing", path=_join(path, name), source=source)


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
    _check_keys(CellSpec.keys(), [], value, "cell", source)
    try:
        return CellSpec.from_keys(value)
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


