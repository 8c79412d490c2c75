"""One-step prediction error of each phase's dynamics (thesis eq. 80-81, fig. 16-20)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from etar.demonstrations import check_demonstrations
from etar.model import ETAR


@dataclass(frozen=True)
class PredictionErrors:
    """``mse[i, j]``: mean squared one-step error of predicting the steps of
    phase i with the parameters of phase j (the thesis' E_{rho_i}(theta_j));
    ``count[i]``: how many steps phase i has.  A good model has the smallest
    entry of each row on the diagonal."""

    mse: np.ndarray  # (K, K)
    count: np.ndarray  # (K,)

    @property
    def diagonal_is_best(self) -> np.ndarray:
        """Per phase (with data): is its own parameter set its best predictor?"""
        rows = self.count > 0
        return np.where(rows, np.argmin(np.where(np.isnan(self.mse), np.inf, self.mse), axis=1)
                        == np.arange(len(self.count)), False)

    def table(self) -> str:
        K = len(self.count)
        head = "phase \\ params " + " ".join(f"{'theta_' + str(j):>12}" for j in range(K)) + "     steps"
        rows = [head]
        for i in range(K):
            cells = " ".join(f"{v:12.4e}" for v in self.mse[i])
            rows.append(f"{'rho_' + str(i):>15} {cells} {self.count[i]:>9d}")
        return "\n".join(rows)


def prediction_errors(model: ETAR, demos: Sequence, labels: Sequence | None = None) -> PredictionErrors:
    """K x K table of one-step prediction errors.

    ``labels``: one phase index per step (T-1,) per demonstration, e.g. ground
    truth; by default the model's own Viterbi segmentation.
    s_hat_{t+1} = A_j s_t + B_j [f_t; 1] (eq. 80), e_t = s_hat_{t+1} - s_{t+1} (eq. 81).
    """
    demos = check_demonstrations(demos, n=model.n_state, m=model.n_force)
    K = model.n_phases
    sq = np.zeros((K, K))
    count = np.zeros(K, dtype=np.int64)
    A, B = np.asarray(model.A), np.asarray(model.B)
    for i, (s, f) in enumerate(demos):
        lab = model.viterbi(s, f) if labels is None else np.asarray(labels[i], dtype=np.int64)
        if lab.shape != (s.shape[0] - 1,):
            raise ValueError(f"labels[{i}] must have shape ({s.shape[0] - 1},), got {lab.shape}")
        if lab.size and (lab.min() < 0 or lab.max() >= K):
            raise ValueError(f"labels[{i}] has phases outside 0..{K - 1}")
        u = np.hstack([f[:-1], np.ones((s.shape[0] - 1, 1))])
        for j in range(K):
            pred = s[:-1] @ A[j].T + u @ B[j].T
            err = ((pred - s[1:]) ** 2).sum(axis=1)
            np.add.at(sq[:, j], lab, err)
        count += np.bincount(lab, minlength=K)
    with np.errstate(invalid="ignore", divide="ignore"):
        mse = sq / count[:, None]
    mse[count == 0] = np.nan
    return PredictionErrors(mse, count)
