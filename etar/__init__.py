"""ETAR: effect-of-action based transitions auto-regressive HMM (learning library).

numpy/scipy (and numba for the inner loops) only; knows nothing of messaging
or physics.  See ``ETAR`` for the model, ``select_order`` for BIC/AIC.
``ETAR`` and its companions are loaded on first use (``etar.vocabulary`` alone
loads nothing: a scenario checks its words without compiling the learner).
"""

__all__ = ["ETAR", "FitReport", "PhaseFilter", "DemonstrationError"]


def __getattr__(name: str):
    if name in ("ETAR", "FitReport", "PhaseFilter"):
        from etar import model

        return getattr(model, name)
    if name == "DemonstrationError":
        from etar.demonstrations import DemonstrationError

        return DemonstrationError
    raise AttributeError(f"module 'etar' has no attribute {name!r}")
