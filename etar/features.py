"""What ETAR sees of the robot: the state and force vectors built from messages.

One definition, used offline (``services.recordings.demonstrations.load_demonstration``, the
learner's input) and online (the phase estimator), so both see the same numbers.

- state ``position``: tcp position, base frame (3,);
  ``pose``: position and the orientation as a rotation vector relative to the
  episode's first orientation (6,).  With a ``resolution`` > 0 the position is
  rounded to a grid of that pitch (m): a coarser state, as a position measured
  by a coarser sensor would be (the controller still sees the KRC's own).
- features ``force``: the F/T force rotated into base axes (3,) - the sensor
  frame has the tcp's orientation; ``force_torque``: force and torque (6,).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from etar.vocabulary import FEATURES, STATES


def pose_of(msr_cart_pos) -> tuple[np.ndarray, np.ndarray]:
    m = np.asarray(msr_cart_pos, dtype=np.float64).reshape(3, 4)
    return m[:, :3], m[:, 3]


def state_vector(msr_cart_pos, kind: str = "position", R0: np.ndarray | None = None,
                 resolution: float = 0.0) -> np.ndarray:
    R, p = pose_of(msr_cart_pos)
    if resolution > 0.0:
        p = np.round(p / resolution) * resolution
    if kind == "position":
        return p.copy()
    if kind == "pose":
        ref = R if R0 is None else R0
        return np.concatenate([p, pin.log3(ref.T @ R)])
    raise ValueError(f"state must be one of {tuple(STATES)}, got {kind!r}")


def force_vector(wrench, msr_cart_pos, kind: str = "force") -> np.ndarray:
    R, _ = pose_of(msr_cart_pos)
    w = np.asarray(wrench, dtype=np.float64)
    if kind == "force":
        return R @ w[:3]
    if kind == "force_torque":
        return np.concatenate([R @ w[:3], R @ w[3:]])
    raise ValueError(f"features must be one of {tuple(FEATURES)}, got {kind!r}")
