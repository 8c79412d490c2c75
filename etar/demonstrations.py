"""Checking demonstrations and turning them into the arrays inference works on.

A demonstration is ``(states, forces)``: ``states`` (T, n) and ``forces`` (T, m)
sampled at the same instants.  Lists of demonstrations may be ragged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


class DemonstrationError(ValueError):
    """A demonstration that cannot be used, with the index and field at fault."""


@dataclass(frozen=True)
class StepArrays:
    """The per-step arrays of one demonstration (see ``etar.inference``)."""

    regressors: np.ndarray  # (T-1, n+m+1) [s_t; f_t; 1]
    next_states: np.ndarray  # (T-1, n) s_{t+1}
    features: np.ndarray  # (T-1, d+1) transition features phi_t


# no state or force in any unit comes near it; squared and summed over thousands of samples,
# a value past ~1e150 overflows float64 and the fit ends in LAPACK's errors
MAX_MAGNITUDE = 1e100


def check_demonstration(states, forces, *, index: int = 0, n: int | None = None, m: int | None = None):
    """Return float64, C-contiguous copies of one demonstration or raise.

    The error names the demonstration, the array and the first bad value.
    """
    where = f"demonstration {index}"
    arrays = []
    for name, value, width in (("states", states, n), ("forces", forces, m)):
        if np.iscomplexobj(value):  # float64 would drop the imaginary part with only a warning
            raise DemonstrationError(f"{where}: {name} is complex ({np.asarray(value).dtype}); expected real numbers")
        try:
            arr = np.array(value, dtype=np.float64, copy=True, order="C")
        except (TypeError, ValueError) as exc:
            raise DemonstrationError(f"{where}: {name} is not a numeric array ({exc})") from None
        if arr.ndim != 2:
            raise DemonstrationError(
                f"{where}: {name} must be 2-D (T, {'n' if name == 'states' else 'm'}), got shape {arr.shape}"
            )
        if width is not None and arr.shape[1] != width:
            raise DemonstrationError(
                f"{where}: {name} has {arr.shape[1]} columns, expected {width} (shape {arr.shape})"
            )
        bad = np.argwhere(~np.isfinite(arr))
        if bad.size:
            t, c = bad[0]
            raise DemonstrationError(
                f"{where}: {name}[{t}, {c}] is {float(arr[t, c])}; "
                f"{len(bad)} non-finite value(s) in all (sensor dropout? remove or interpolate them)"
            )
        huge = np.argwhere(np.abs(arr) > MAX_MAGNITUDE)
        if huge.size:
            t, c = huge[0]
            raise DemonstrationError(
                f"{where}: {name}[{t}, {c}] is {float(arr[t, c]):g}; values past {MAX_MAGNITUDE:g} overflow the "
                "fit's sums of squares (wrong units?)"
            )
        arrays.append(arr)
    s, f = arrays
    if s.shape[0] != f.shape[0]:
        raise DemonstrationError(
            f"{where}: states has {s.shape[0]} samples but forces has {f.shape[0]}; "
            "they must be sampled at the same instants"
        )
    if s.shape[0] < 2:
        raise DemonstrationError(f"{where}: needs at least 2 samples, got {s.shape[0]}")
    if s.shape[1] == 0:
        raise DemonstrationError(f"{where}: states has no columns")
    return s, f


def check_true_labels(labels, samples: int, where: str) -> None:
    """A demonstration's true phases (``etar.task.learn_task`` matches the learned ones to them):
    whole numbers >= 0 in one row, one per sample or per step, or a DemonstrationError."""
    try:
        whole = np.asarray(labels, dtype=np.float64)
        ok = whole.ndim == 1 and bool(np.all(np.isfinite(whole) & (whole >= 0) & (whole == np.round(whole))))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise DemonstrationError(f"{where}: field 'phases' must be whole numbers >= 0 in one row (true labels), "
                                 f"got {np.asarray(labels).dtype} of shape {np.shape(labels)}")
    if len(labels) not in (samples, samples - 1):
        raise DemonstrationError(f"{where}: field 'phases' has {len(labels)} labels; expected one per sample "
                                 f"({samples}) or per step ({samples - 1})")


def check_demonstrations(demos: Sequence, *, n: int | None = None, m: int | None = None):
    """Check a (possibly ragged) list of demonstrations; all must share n and m."""
    if isinstance(demos, tuple) and len(demos) == 2 and np.ndim(demos[0]) == 2:
        raise DemonstrationError(
            "expected a list of demonstrations [(states, forces), ...], got a single (states, forces) pair"
        )
    demos = list(demos)
    if not demos:
        raise DemonstrationError("no demonstrations given")
    out = []
    for i, demo in enumerate(demos):
        try:
            states, forces = demo
        except (TypeError, ValueError):
            raise DemonstrationError(
                f"demonstration {i}: expected a (states, forces) pair, got {type(demo).__name__}"
            ) from None
        s, f = check_demonstration(states, forces, index=i, n=n, m=m)
        n, m = s.shape[1], f.shape[1]
        out.append((s, f))
    return out


def transition_features(states: np.ndarray, forces: np.ndarray, transitions: str, goal) -> np.ndarray:
    """phi_t for t = 0..T-2: [f_t; 1] (ETAR) or [s_t - goal; 1] (STAR)."""
    if transitions == "effect":
        base = forces[:-1]
    else:
        base = states[:-1] - np.asarray(goal, dtype=np.float64)
    return np.hstack([base, np.ones((base.shape[0], 1))])


def step_arrays(states: np.ndarray, forces: np.ndarray, transitions: str, goal=None) -> StepArrays:
    """Build regressors, next states and transition features of one demonstration.

    For STAR without an explicit goal the demonstration's own end point is used.
    """
    if transitions == "state" and goal is None:
        goal = states[-1]
    regressors = np.hstack([states[:-1], forces[:-1], np.ones((states.shape[0] - 1, 1))])
    return StepArrays(
        regressors=np.ascontiguousarray(regressors),
        next_states=np.ascontiguousarray(states[1:]),
        features=np.ascontiguousarray(transition_features(states, forces, transitions, goal)),
    )
