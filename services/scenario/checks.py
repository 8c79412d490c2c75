"""The vocabulary of a scenario and the checks of its values: each returns the
normalised value or raises a ``ScenarioError`` naming the field."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from etar.vocabulary import CRITERIA, MAX_PHASES, TRANSITIONS  # noqa: F401  (CRITERIA: the stages check it)
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
            parts.append(shorten(self.path, MAX_PATH))
        parts.append(f"{self.problem}, got {quoted(self.value)}" if self.has_value else self.problem)
        return ": ".join(parts)

    def within(self, prefix: str = "", source: str | None = None) -> ScenarioError:
        """The same error seen from further out: ``prefix`` goes in front of the path."""
        return ScenarioError(self.problem, path=_join(prefix, self.path), value=self.value,
                             source=self.source if source is None else source, line=self.line)


# An error is one line a person reads: a value pasted by mistake (a whole file, an anchor
# bomb's millions of items) is shown by its start and its size, never printed whole.
MAX_QUOTED = 80  # characters of a value quoted in an error
MAX_PATH = 120  # characters of a field path (an unknown key is part of it)


class _Full(Exception):
    """The quoted text has reached its length: stop walking the value."""


def quoted(value: Any, limit: int = MAX_QUOTED) -> str:
    """``repr(value)``, cut to ``limit`` characters with an ellipsis and the value's size.

    The value is walked only as far as the text reaches, so a nested, shared (YAML
    aliases) or self-containing value costs ``limit`` steps, never its expanded size.
    """
    parts: list[str] = []
    room = [limit + 1]

    def put(text: str) -> None:
        parts.append(text[:room[0]])
        room[0] -= len(text)
        if room[0] <= 0:
            raise _Full

    def walk(item: Any) -> None:
        if isinstance(item, (list, tuple, Mapping)):
            ends = "{}" if isinstance(item, Mapping) else "()" if isinstance(item, tuple) else "[]"
            put(ends[0])
            pairs = item.items() if isinstance(item, Mapping) else ((_NOTHING, x) for x in item)
            for i, (key, x) in enumerate(pairs):
                put(", " if i else "")
                if key is not _NOTHING:
                    walk(key)
                    put(": ")
                walk(x)
            put("," + ends[1] if isinstance(item, tuple) and len(item) == 1 else ends[1])
        elif isinstance(item, str):
            put(repr(item[:room[0]]) if len(item) > room[0] else repr(item))
        elif _is_int(item):
            put(_digits(item))
        else:
            put(repr(item))

    try:
        walk(value)
    except _Full:
        return "".join(parts)[:limit] + f"... ({_size(value)})"
    return "".join(parts)


def _digits(value: Any) -> str:
    try:
        return repr(value)
    except ValueError:  # past sys.get_int_max_str_digits (4300): str() would take quadratic time
        return f"<an integer of about {int(int(value).bit_length() * math.log10(2)) + 1} digits>"


def _size(value: Any) -> str:
    if _is_int(value):
        digits = _digits(abs(int(value)))
        return f"{len(digits)} digits" if digits.isdigit() else digits
    if isinstance(value, str):
        return f"{len(value)} characters"
    if isinstance(value, Mapping):
        return f"a mapping of {len(value)} keys"
    if isinstance(value, (list, tuple)):
        return f"a {'list' if isinstance(value, list) else 'tuple'} of {len(value)} items"
    return type(value).__name__


def shorten(text: str, limit: int) -> str:
    """``text`` cut to ``limit`` characters with an ellipsis and its length."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


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
    if not _is_int(value) or not 1 <= value <= MAX_PHASES:
        raise ScenarioError(f"expected 'auto' or an integer >= 1 and <= {MAX_PHASES}", path=name, value=value)
    return int(value)


def _candidates(value: Any, name: str) -> tuple[int, ...]:
    items = _list(value, name, f"phase counts (integers >= 1 and <= {MAX_PHASES})")
    if not items:
        raise ScenarioError("expected at least one phase count", path=name, value=value)
    counts = tuple(_int(v, f"{name}[{i}]", 1, MAX_PHASES) for i, v in enumerate(items))
    if len(set(counts)) != len(counts):
        raise ScenarioError("expected distinct phase counts", path=name, value=value)
    return counts


def _set(obj: Any, name: str, value: Any) -> None:
    # Normalising inside __post_init__ of a frozen dataclass (lists to tuples, ints to
    # floats) is the one place the objects are written after creation.
    object.__setattr__(obj, name, value)

