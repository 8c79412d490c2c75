"""Synthetic demonstrations drawn from a known ETAR model (for tests and benchmarks).

The phases differ in how force turns into motion, as real contact phases do
(DESIGN.md, "Identifiability"): in phase 0 the hand's force moves the tool
freely; in every later phase a surface absorbs the force along its own normal.
A simulated teacher raises the contact force towards the level of the next
phase on a schedule; the phase itself is then drawn from the model's softmax
transitions given that force, so the labels are samples of the true model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from etar.model import ETAR


@dataclass(frozen=True)
class SyntheticTask:
    model: ETAR  # the true parameters
    force_levels: np.ndarray  # (K, m) the teacher's force in each phase
    force_noise: float  # N, standard deviation around the level


def make_task(n_phases: int = 3, seed: int = 0, *, n: int = 3, m: int = 3, gain: float = 1e-3,
              speed: float = 1e-3, noise: float = 1e-4, force_noise: float = 1.0,
              level: float = 8.0, sharpness: float = 0.5) -> SyntheticTask:
    """A K-phase task with the valley's structure (free motion, then contacts).

    ``gain`` m/N per step of free motion; ``speed`` m per step of drift along each
    phase's direction; ``noise`` m, per-axis standard deviation of the step noise.
    """
    for name, value in (("n_phases", n_phases), ("n", n), ("m", m)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    rng = np.random.default_rng(seed)
    K = n_phases
    levels = np.zeros((K, m))
    for j in range(1, K):
        while True:
            cand = rng.normal(size=m)
            cand *= level / np.linalg.norm(cand)
            if all(np.linalg.norm(cand - levels[i]) > 0.8 * level for i in range(j)):
                break
        levels[j] = cand
    A = np.repeat(np.eye(n)[None], K, axis=0)
    B = np.zeros((K, n, m + 1))
    k = min(n, m)
    for j in range(K):
        P = np.eye(n)
        if j > 0:
            normal = rng.normal(size=n)
            normal /= np.linalg.norm(normal)
            P = P - np.outer(normal, normal)
        B[j, :, :k] = gain * P[:, :k]
        drift = rng.normal(size=n)
        B[j, :, m] = speed * drift / np.linalg.norm(drift) - B[j, :, :m] @ levels[j]
    Sigma = np.repeat((noise**2 * np.eye(n))[None], K, axis=0)
    W = np.zeros((K + 1, K, m + 1))
    W[0, 0, m] = 10.0  # start in phase 0
    for i in range(K):
        for j in range(K):
            if j < i or j > i + 1:
                W[i + 1, j, m] = -20.0  # (almost) never go back or skip
        if i + 1 < K:
            # switch once the force is three quarters of the way to the next level
            # (hysteresis: noise around the current level rarely crosses it)
            dL = levels[i + 1] - levels[i]
            W[i + 1, i + 1, :m] = sharpness * dL
            W[i + 1, i + 1, m] = -sharpness * (dL @ levels[i] + 0.75 * dL @ dL)
    model = ETAR(K)
    model.A, model.B, model.Sigma, model.W = A, B, Sigma, W
    return SyntheticTask(model, levels, force_noise)


def sample_demonstrations(task: SyntheticTask, n_demos: int, length: int | tuple, seed: int):
    """Draw demonstrations: list of (states (T, n), forces (T, m), phases (T-1,)).

    ``length`` is T, or a (low, high) range for ragged demonstrations; T >= 2.
    """
    if isinstance(n_demos, bool) or not isinstance(n_demos, (int, np.integer)) or n_demos < 0:
        raise ValueError(f"n_demos must be an integer >= 0, got {n_demos!r}")
    low, high = length if isinstance(length, tuple) else (length, length)
    if not 2 <= low <= high:
        raise ValueError(f"length must be a number of samples >= 2 or a range (low, high) with 2 <= low <= high, "
                         f"got {length!r}")
    rng = np.random.default_rng(seed)
    model = task.model
    K, n = model.A.shape[:2]
    m = model.B.shape[2] - 1
    C = np.concatenate([model.A, model.B], axis=2)
    chol = np.linalg.cholesky(model.Sigma)
    demos = []
    for _ in range(n_demos):
        T = int(rng.integers(length[0], length[1] + 1)) if isinstance(length, tuple) else int(length)
        # the teacher's schedule: when it starts pushing towards each next phase
        bounds = np.sort(rng.uniform(0.6, 1.4, size=K) * (T - 1) / K).cumsum()
        bounds = bounds * (T - 1) / bounds[-1]
        states = np.zeros((T, n))
        forces = np.zeros((T, m))
        phases = np.zeros(T - 1, dtype=np.int64)
        states[0] = rng.normal(scale=0.05, size=n) + np.array([0.5, 0.0, 0.4, 0.0, 0.0, 0.0][:n] + [0.0] * max(0, n - 6))
        for t in range(T - 1):
            intended = int(np.searchsorted(bounds, t, side="right"))
            intended = min(intended, K - 1)
            forces[t] = task.force_levels[intended] + rng.normal(scale=task.force_noise, size=m)
            phi = np.append(forces[t], 1.0)
            row = model.W[0] if t == 0 else model.W[phases[t - 1] + 1]
            logits = row @ phi
            p = np.exp(logits - logits.max())
            phases[t] = rng.choice(K, p=p / p.sum())
            x = np.concatenate([states[t], phi])
            states[t + 1] = C[phases[t]] @ x + chol[phases[t]] @ rng.normal(size=n)
        forces[T - 1] = task.force_levels[phases[-1]] + rng.normal(scale=task.force_noise, size=m)
        demos.append((states, forces, phases))
    return demos
