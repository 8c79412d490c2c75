"""The learned task: everything a reproduction needs, typed and checked once.

A ``LearnedTask`` is the fitted ETAR model plus what was learned beside it from
the same demonstrations: each phase's impedance (``etar.impedance``), the goal
(the demonstrations' mean end position, and with a pose state their mean final
turn), the sampling period, which state and features the model sees, and, when
the demonstrations carry true phase labels, which learned phase is which true
phase (Hungarian matching on the demonstrations, never on a reproduction).

``learn_task`` makes one from a fitted model and its demonstrations, the same
for ``etar learn`` and the scenario runner; ``save``/``load_task`` keep it in
the model file (the model's ``metadata``, docs/model-format.md), so a model
learned by either can be reproduced by a scenario's ``model:``.  Construction
validates everything (shapes, finiteness, positive-definite covariances, one
impedance per phase, a goal); a problem raises ``TaskError`` naming the file,
the field and the value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from etar.impedance import PhaseImpedance, impedance_from_file, phase_impedances
from etar.metrics import match_phases
from etar.model import ETAR
from etar.vocabulary import FEATURES, STATES



class TaskError(ValueError):
    """A learned task that cannot be used: ``source: field: problem, got value``."""

    def __init__(self, source: str, field_name: str, problem: str, value=None, has_value: bool = True):
        self.source, self.field, self.problem = source, field_name, problem
        text = f"{source}: {field_name}: {problem}"
        if has_value:
            text += f", got {_short(value)}"
        super().__init__(text)


def _short(value) -> str:
    text = repr(value.tolist() if hasattr(value, "tolist") else value)
    return text if len(text) <= 120 else text[:117] + "..."


@dataclass(frozen=True)
class LearnedTask:
    model: ETAR
    impedances: tuple  # one PhaseImpedance (or None: a phase without enough data) per phase
    goal: np.ndarray  # (3,) m: where the demonstrations ended, on average
    dt: float  # s between samples
    state: str = "position"
    features: str = "force"
    state_resolution: float = 0.0  # m: the grid the state's position was rounded to (0: none)
    goal_rotation: np.ndarray | None = None  # (3,) rad: pose state only, the mean final turn
    phase_to_truth: dict | None = None  # learned phase -> true phase, from the demonstrations' labels
    selection: dict | None = None  # how the number of phases was chosen (etar.selection summary)
    demonstrations: tuple = ()  # where the demonstrations came from
    source: str = field(default="<memory>", compare=False)

    def __post_init__(self):
        self._validate()

    @property
    def n_phases(self) -> int:
        return self.model.n_phases

    def _fail(self, name, problem, value=None, has_value=True):
        raise TaskError(self.source, name, problem, value, has_value)

    def _validate(self) -> None:
        model, K = self.model, self.model.n_phases
        if self.state not in STATES:
            self._fail("metadata.state", f"expected one of {sorted(STATES)}", self.state)
        if self.features not in FEATURES:
            self._fail("metadata.features", f"expected one of {sorted(FEATURES)}", self.features)
        if model.n_state != STATES[self.state]:
            self._fail("metadata.state", f"the model's state has {model.n_state} columns; "
                                         f"{self.state!r} has {STATES[self.state]}", self.state)
        res = self.state_resolution
        if isinstance(res, bool) or not isinstance(res, (int, float)) or not (math.isfinite(res) and res >= 0):
            self._fail("metadata.state_resolution", "expected a grid pitch >= 0 m (0: the state is not rounded)", res)
        object.__setattr__(self, "state_resolution", float(res))
        if model.n_force != FEATURES[self.features]:
            self._fail("metadata.features", f"the model's force has {model.n_force} columns; "
                                            f"{self.features!r} has {FEATURES[self.features]}", self.features)
        if not (isinstance(self.dt, (int, float)) and math.isfinite(self.dt) and self.dt > 0):
            self._fail("metadata.dt", "expected a sampling period > 0 s", self.dt)
        goal = np.asarray(self.goal, dtype=np.float64)
        if goal.shape != (3,) or not np.all(np.isfinite(goal)):
            self._fail("metadata.goal", "expected 3 finite numbers (m)", self.goal)
        object.__setattr__(self, "goal", goal)
        if self.goal_rotation is not None:
            rot = np.asarray(self.goal_rotation, dtype=np.float64)
            if rot.shape != (3,) or not np.all(np.isfinite(rot)):
                self._fail("metadata.goal_rotation", "expected 3 finite numbers (rad) or null", self.goal_rotation)
            object.__setattr__(self, "goal_rotation", rot)
        imps = tuple(self.impedances)
        if len(imps) != K:
            self._fail("metadata.impedance", f"expected one entry per phase ({K})", f"{len(imps)} entries")
        for j, imp in enumerate(imps):
            if imp is not None:
                _check_impedance(imp, f"metadata.impedance[{j}]", K, self._fail)
        if all(imp is None for imp in imps):
            self._fail("metadata.impedance", "no phase has an impedance: there is nothing to reproduce", None,
                       has_value=False)
        object.__setattr__(self, "impedances", imps)
        if self.phase_to_truth is not None:
            mapping = {}
            for k, v in dict(self.phase_to_truth).items():
                try:
                    kk, vv = int(k), int(v)
                except (TypeError, ValueError):
                    self._fail("metadata.phase_to_truth", "expected integer phases", {k: v})
                if not 0 <= kk < K or vv < 0:
                    self._fail("metadata.phase_to_truth", f"learned phases are 0..{K - 1}, true phases >= 0",
                               {k: v})
                mapping[kk] = vv
            object.__setattr__(self, "phase_to_truth", mapping or None)
        sel = self.selection
        if sel is not None and not (isinstance(sel, dict) and isinstance(sel.get("criterion", ""), str)
                                    and isinstance(sel.get("per_demonstration", []), list)):
            self._fail("metadata.selection", "expected how the number of phases was chosen (an object with "
                                             "criterion, best, scores) or null", sel)
        object.__setattr__(self, "demonstrations", tuple(str(d) for d in self.demonstrations))

    # ------------------------------------------------------------ files

    def to_model(self) -> ETAR:
        """The model with this task in its metadata (what ``save`` writes)."""
        meta = dict(self.model.metadata)
        meta.update(impedance=[None if i is None else i.to_dict() for i in self.impedances], dt=float(self.dt),
                    state=self.state, features=self.features, goal=self.goal.tolist(),
                    demonstrations=list(self.demonstrations))
        if self.state_resolution:
            meta["state_resolution"] = self.state_resolution
        if self.goal_rotation is not None:
            meta["goal_rotation"] = self.goal_rotation.tolist()
        if self.phase_to_truth is not None:
            meta["phase_to_truth"] = {str(k): int(v) for k, v in self.phase_to_truth.items()}
        if self.selection is not None:
            meta["selection"] = self.selection
        self.model.metadata = meta
        return self.model

    def save(self, path) -> Path:
        path = Path(path).expanduser().resolve()
        path.parent.mkdir(parents=True, exist_ok=True)
        self.to_model().save(path)
        return path

    @classmethod
    def from_model(cls, model: ETAR, source: str = "<memory>") -> "LearnedTask":
        meta = model.metadata
        if not meta.get("impedance"):
            raise TaskError(source, "metadata.impedance", "missing: the model has no per-phase impedance; learn "
                            "it with `etar learn` or a scenario's learn stage", has_value=False)
        if meta.get("goal") is None:
            raise TaskError(source, "metadata.goal", "missing: the model does not say where the task ends; "
                            "learn it with this version of `etar learn` or a scenario's learn stage",
                            has_value=False)
        imps = []
        for j, d in enumerate(meta["impedance"]):
            if d is None:
                imps.append(None)
                continue
            try:
                imps.append(impedance_from_file(d))
            except (KeyError, TypeError, ValueError) as exc:
                raise TaskError(source, f"metadata.impedance[{j}]", f"not a phase impedance ({exc})",
                                d) from None
        state = meta.get("state") or ("pose" if model.n_state == 6 else "position")
        features = meta.get("features") or ("force_torque" if model.n_force == 6 else "force")
        return cls(model=model, impedances=tuple(imps), goal=meta["goal"], dt=meta.get("dt", 0.01), state=state,
                   features=features, state_resolution=meta.get("state_resolution", 0.0),
                   goal_rotation=meta.get("goal_rotation"),
                   phase_to_truth=meta.get("phase_to_truth") or None, selection=meta.get("selection"),
                   demonstrations=tuple(meta.get("demonstrations") or ()), source=source)


def _check_impedance(imp, name: str, K: int, fail) -> None:
    if not isinstance(imp, PhaseImpedance):
        fail(name, "expected a PhaseImpedance", imp)

    def vec(attr, shape):
        v = np.asarray(getattr(imp, attr), dtype=np.float64)
        if v.shape != shape or not np.all(np.isfinite(v)):
            fail(f"{name}.{attr}", f"expected finite numbers of shape {shape}", getattr(imp, attr))
        return v

    d = vec("direction", (3,))
    if abs(np.linalg.norm(d) - 1.0) > 1e-6:
        fail(f"{name}.direction", "expected a unit vector", d)
    if imp.n_compliant not in (0, 1, 2):
        fail(f"{name}.n_compliant", "expected 0, 1 or 2", imp.n_compliant)
    vec("compliant_axes", (imp.n_compliant, 3))
    K_ = vec("stiffness", (3, 3))
    if not np.allclose(K_, K_.T, atol=1e-9 * max(1.0, np.abs(K_).max())):
        fail(f"{name}.stiffness", "expected a symmetric matrix (K = R V R^T)", K_)
    if np.linalg.eigvalsh(K_).min() < -1e-9 * max(1.0, np.abs(K_).max()):
        fail(f"{name}.stiffness", "expected a positive semi-definite matrix (K = R V R^T)", K_)
    vec("mean_force", (3,))
    vec("angular_velocity", (3,))
    if imp.mean_position is not None:
        vec("mean_position", (3,))
    if not (math.isfinite(imp.mean_speed) and imp.mean_speed >= 0.0):
        fail(f"{name}.mean_speed", "expected a finite speed >= 0 m/s", imp.mean_speed)
    if imp.successor is not None and not 0 <= imp.successor < K:
        fail(f"{name}.successor", f"expected a phase 0..{K - 1} or null", imp.successor)


def load_task(path) -> LearnedTask:
    """Read a model file and the task learned with it; every problem is one error naming the file."""
    source = str(path)
    try:
        model = ETAR.load(path)
    except ValueError as exc:
        raise TaskError(source, "model", str(exc).removeprefix(f"{source}: "), has_value=False) from None
    return LearnedTask.from_model(model, source)


def infer_kinds(model: ETAR) -> tuple[str, str]:
    """(state, features) of a model from its dimensions: a 6-column state is a pose."""
    state = "pose" if model.n_state == 6 else "position"
    features = "force_torque" if model.n_force == 6 else "force"
    return state, features


def learn_task(model: ETAR, demos, dt: float, *, state: str | None = None, features: str | None = None,
               state_resolution: float = 0.0, selection: dict | None = None, sources=(), source: str = "<memory>") -> LearnedTask:
    """The task a fitted ``model`` learned from ``demos``.

    ``demos``: dicts with ``states`` (T, n), ``forces`` (T, m) and optionally
    ``phases`` (T,) true labels, or (states, forces) pairs.  Each phase's
    impedance comes from the Viterbi segmentation of the demonstrations
    (``etar.impedance.phase_impedances``); the goal is the mean final position;
    with a pose state the goal also has the mean final turn; with labels on every
    demonstration, ``phase_to_truth`` matches learned to true phases.
    """
    items = [d if isinstance(d, dict) else {"states": d[0], "forces": d[1]} for d in demos]
    pairs = [(np.asarray(d["states"], dtype=np.float64), np.asarray(d["forces"], dtype=np.float64)) for d in items]
    if not pairs:
        raise ValueError("learn_task needs at least one demonstration")
    guessed = infer_kinds(model)
    state = state or guessed[0]
    features = features or guessed[1]
    pose = state == "pose"
    imps = phase_impedances(model, pairs, dt, rotation_columns=slice(3, 6) if pose else None)
    goal = np.mean([s[-1][:3] for s, _ in pairs], axis=0)
    # the mean final turn, relative to each demonstration's first orientation
    goal_rotation = np.mean([s[-1][3:6] for s, _ in pairs], axis=0) if pose else None
    mapping = None
    if all(d.get("phases") is not None for d in items):
        # labels of the T-1 steps; a label per sample (T) gives step t -> t+1 the label at t+1
        truth = np.concatenate([np.asarray(d["phases"])[1:] if len(d["phases"]) == len(s) else np.asarray(d["phases"])
                                for d, (s, _) in zip(items, pairs)])
        pred = np.concatenate([model.viterbi(s, f) for s, f in pairs])
        if len(truth) == len(pred):
            mapping = match_phases(truth, pred, n_pred=model.n_phases)
    return LearnedTask(model=model, impedances=tuple(imps), goal=goal, dt=float(dt), state=state, features=features,
                       state_resolution=state_resolution, goal_rotation=goal_rotation, phase_to_truth=mapping, selection=selection,
                       demonstrations=tuple(str(s) for s in sources), source=source)
