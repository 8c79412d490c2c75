"""The vocabulary of a scenario and the checks of its values: each returns the
normalised value or raises a ``ScenarioError`` naming the field."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from etar.vocabulary import CRITERIA, TRANSITIONS  # noqa: F401  (CRITERIA: the stages check it)
from etar.vocabulary import FEATURES as ETAR_FEATURES, STATES as ETAR_STATES
from robot_sim.world.tasks import TASK_WORLDS

WORLDS = TASK_WORLDS
RESTART_POLICIES = ("never", "on_failure")
STATES = tuple(ETAR_STATES)  # what ETAR's state and features can be (etar.features)
FEATURES = tuple(ETAR_FEATURES)
SIDES = ("left", "right")
SELECTIONS = ("per_demonstration", "pooled")

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



# what one scenario may ask for, checked before anything starts: a typo such as
# count: 1000000000000 was accepted and grew the runner's memory at 44 MB/s
MAX_EPISODES = 10_000  # per stage
MAX_EPISODE_SECONDS = 3600.0  # simulated, per episode
# a learn stage's effort: past these a fit would take days, so the number is a typo
MAX_RESTARTS = 1_000
MAX_EM_ITERATIONS = 100_000
MAX_PHYSICS_SUBSTEPS = 100  # per FRI cycle: 10 us steps, a hundred times the shipped cost


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
    try:
        x = float(value)
    except OverflowError:  # YAML's integers have no bound
        raise ScenarioError(f"{expected}; this integer has {len(str(abs(int(value))))} digits",
                            path=name, value="an integer too large for a float") from None
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

