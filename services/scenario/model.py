"""The scenario as a value: ``Scenario``, validated on construction, varied with ``replace``."""

from __future__ import annotations

import dataclasses
import difflib
import re
from collections.abc import Mapping
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

import yaml

from services.runtime.cycle import CLOCKS
from services.runtime.roles import CELL_ROLES, RESTARTABLE, STAGE_ROLES
from services.scenario.checks import (FEATURES, RESTART_POLICIES, STATES, WORLDS, ScenarioError, _choice, _join,
                                      _list, _number, _seed, _set, _text, quoted)
from services.scenario.stages import (STAGE_TYPES, CellSpec, DemonstrateStage, LearnStage, ReproduceStage, Stage,
                                      _check_stage_order, doc)
from services.scenario.starts import DEMONSTRATE_SEED_OFFSET, REPRODUCE_SEED_OFFSET

_NAME = re.compile(r"^[A-Za-z0-9_\-]{1,55}$")


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """A whole run: the world, the clock, the seeds and the stages, defaults filled in.

    ``source`` names where the description came from (a file name, or "<dict>"); it is
    used in error messages and is not part of `to_dict`.
    """

    name: str = doc("the run's name (its run id begins with it)")
    description: str = doc('one line on what the scenario is for', "")
    world: str = doc('valley | hose_coupler')
    clock: str = doc('lockstep (every FRI cycle waits for its answers: deterministic) | realtime (1 ms wall-clock deadlines, over Zenoh only)', "lockstep")
    seed: int = doc('int >= 0: the base seed of the cell, the sensor and every stage', 0)
    state: str = doc('position | pose: what ETAR uses as its state', "position")
    features: str = doc("force | force_torque: ETAR's transition and effect features", "force")
    state_resolution: float = doc("m >= 0: ETAR's state position rounded to a grid of this pitch, offline and online (0: not rounded); the arm's control is not", 0.0)
    model: str | None = doc('a model file learned earlier (relative to the scenario file): the reproductions use it instead of a learn stage', None)
    cell: CellSpec = doc("the simulated cell's physics and devices (below)", CellSpec())
    restart: Any = doc('per service, what the runner does if it dies mid-run: never (the run fails) | on_failure (started again: a recorder writes on in a new file and the report names the gap, an estimator re-synchronises its filter); recorder and phase_estimator only', ())
    stages: tuple[Stage, ...] = doc('a non-empty list, each item one key: demonstrate, learn or reproduce (below)')
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
        if not _NAME.match(self.name):
            # a run's id is the name and 9 characters more, and the id is a Zenoh key's part
            raise ScenarioError("use 1-55 letters, digits, '-' or '_' (the run's id and its Zenoh keys are made "
                                "from it)", path="name", value=self.name)
        _text(self.description, "description")
        _choice(self.world, "world", WORLDS)
        _choice(self.clock, "clock", CLOCKS)
        _set(self, "seed", _seed(self.seed, "seed"))
        _choice(self.state, "state", STATES)
        _choice(self.features, "features", FEATURES)
        _set(self, "state_resolution", _number(self.state_resolution, "state_resolution", 0.0))
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
        return CELL_ROLES + tuple(r for kind, roles in STAGE_ROLES.items() if kind in kinds for r in roles)

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
                                source=f"{self.source} with {path} = {quoted(value)}") from None

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
        if not self.state_resolution:
            del out["state_resolution"]  # as before the key existed: a run's scenario file is unchanged
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
        if i >= len(stages):  # the index is at fault, not the value
            raise ScenarioError(f"the scenario has {len(stages)} {m['kind']} stage(s), index 0..{len(stages) - 1}",
                                path=path, value=i)
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


