"""Scoring a phase segmentation against ground truth."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SegmentationScore:
    accuracy: float  # fraction of steps whose (matched) phase is right
    mapping: dict  # predicted phase -> true phase (Hungarian matching)
    transition_errors: np.ndarray  # seconds, one per matched true transition
    missed_transitions: int  # true transitions with no predicted counterpart
    spurious_switches: int  # predicted switches that match no true transition

    @property
    def mean_transition_error(self) -> float:
        return float(np.mean(self.transition_errors)) if self.transition_errors.size else float("nan")

    @property
    def max_transition_error(self) -> float:
        return float(np.max(self.transition_errors)) if self.transition_errors.size else float("nan")

    def to_dict(self) -> dict:
        return dict(
            accuracy=self.accuracy,
            mapping={int(k): int(v) for k, v in self.mapping.items()},
            transition_errors_s=[float(e) for e in self.transition_errors],
            mean_transition_error_s=self.mean_transition_error,
            max_transition_error_s=self.max_transition_error,
            missed_transitions=self.missed_transitions,
            spurious_switches=self.spurious_switches,
        )


def match_phases(true, pred, n_true: int | None = None, n_pred: int | None = None) -> dict:
    """Predicted phase -> true phase maximising agreement (Hungarian algorithm)."""
    true = np.asarray(true, dtype=np.int64)
    pred = np.asarray(pred, dtype=np.int64)
    n_true = int(true.max()) + 1 if n_true is None else n_true
    n_pred = int(pred.max()) + 1 if n_pred is None else n_pred
    # imported here: every service imports this module (through etar.task) and only scoring needs
    # scipy.optimize, a quarter of a second of each process's start-up
    from scipy.optimize import linear_sum_assignment

    confusion = np.zeros((n_pred, n_true))
    np.add.at(confusion, (pred, true), 1)
    rows, cols = linear_sum_assignment(-confusion)
    return {int(r): int(c) for r, c in zip(rows, cols)}


def _switches(labels):
    idx = np.flatnonzero(np.diff(labels)) + 1
    return [(int(t), int(labels[t - 1]), int(labels[t])) for t in idx]


def score_segmentation(true, pred, dt: float = 1.0, mapping: dict | None = None,
                       n_true: int | None = None, n_pred: int | None = None) -> SegmentationScore:
    """Accuracy after Hungarian matching, transition-time errors, spurious switches.

    Each true transition a->b is matched to the nearest unmatched predicted
    switch that (after mapping) is also a->b; its time error is |t_pred - t_true| * dt.
    A predicted phase with no matched true phase maps to -1 (always wrong).
    """
    true = np.asarray(true, dtype=np.int64)
    pred = np.asarray(pred, dtype=np.int64)
    if true.shape != pred.shape or true.ndim != 1:
        raise ValueError(f"true and pred must be 1-D of equal length, got {true.shape} and {pred.shape}")
    if true.size == 0:
        raise ValueError("empty segmentation")
    if mapping is None:
        mapping = match_phases(true, pred, n_true, n_pred)
    mapped = np.array([mapping.get(int(p), -1) for p in pred], dtype=np.int64)
    accuracy = float(np.mean(mapped == true))
    true_sw = _switches(true)
    pred_sw = _switches(mapped)
    used = set()
    errors = []
    missed = 0
    for t, a, b in true_sw:
        best, best_k = None, None
        for k, (tp, ap, bp) in enumerate(pred_sw):
            if k in used or (ap, bp) != (a, b):
                continue
            if best is None or abs(tp - t) < best:
                best, best_k = abs(tp - t), k
        if best_k is None:
            missed += 1
        else:
            used.add(best_k)
            errors.append(best * dt)
    spurious = len(pred_sw) - len(used)
    return SegmentationScore(accuracy, mapping, np.array(errors, dtype=np.float64), missed, spurious)


def score_demonstrations(trues, preds, dt: float = 1.0, n_true: int | None = None, n_pred: int | None = None):
    """Score several demonstrations with one phase mapping shared by all of them.

    Returns (overall, per_demonstration): the overall accuracy is over all steps,
    transition errors are pooled and the counts summed.
    """
    trues = [np.asarray(t, dtype=np.int64) for t in trues]
    preds = [np.asarray(p, dtype=np.int64) for p in preds]
    if len(trues) != len(preds) or not trues:
        raise ValueError(f"need equally many true and predicted segmentations, got {len(trues)} and {len(preds)}")
    mapping = match_phases(np.concatenate(trues), np.concatenate(preds), n_true, n_pred)
    per = [score_segmentation(t, p, dt, mapping) for t, p in zip(trues, preds)]
    total = sum(t.size for t in trues)
    overall = SegmentationScore(
        accuracy=float(sum(s.accuracy * t.size for s, t in zip(per, trues)) / total),
        mapping=mapping,
        transition_errors=np.concatenate([s.transition_errors for s in per]),
        missed_transitions=sum(s.missed_transitions for s in per),
        spurious_switches=sum(s.spurious_switches for s in per),
    )
    return overall, per
