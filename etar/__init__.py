"""ETAR: effect-of-action based transitions auto-regressive HMM (learning library).

numpy/scipy (and numba for the inner loops) only; knows nothing of messaging
or physics.  See ``ETAR`` for the model, ``select_order`` for BIC/AIC.
"""

from etar.demonstrations import DemonstrationError
from etar.model import ETAR, FitReport, PhaseFilter

__all__ = ["ETAR", "FitReport", "PhaseFilter", "DemonstrationError"]
