"""An optional per-axis Kalman smoother of the sensor's wrench stream (filterpy), tuned
from the sensor's own noise and resolution."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from robot_sim.ati.sensor import AtiConfig
from robot_sim.cycle import FRI_CYCLE_NS


class WrenchKalmanFilter:
    """Optional per-axis Kalman smoother of a wrench stream (filterpy ``KalmanFilter``).

    Models (each axis independent, same sample period ``dt``):

    * ``"constant"`` (default): the wrench is a random walk, ``w_k+1 = w_k + q·n``,
      measured as ``z = w + r·n``.  In steady state this is an exponential smoother
      with gain α, α²/(1-α) = (q/r)²; default tuning q/r = 0.1 gives α ≈ 0.095:
      noise std ÷ ≈ 4.5 and 95 % of a step within 31 samples (31 ms at 1 kHz).
    * ``"rate"``: state (w, dw/dt) with piecewise-constant white acceleration of std
      ``q`` (filterpy ``Q_discrete_white_noise``).  Follows ramps without lag, but
      overshoots steps (≈ 20 %).  Default tracking index q·dt²/r = 0.01 gives the α-β
      gains α ≈ 0.13, β ≈ 0.009: noise std ÷ ≈ 3, settles to 5 % of a step in ≈ 45
      samples.

    ``measurement_std`` (r) should be the sensor's noise including quantisation,
    ``sqrt(noise² + step²/12)``; :meth:`for_sensor` computes it from an
    :class:`AtiConfig`.  The filter starts at the first finite measurement (zero rate)
    with the steady-state covariance (discrete Riccati solution), so its gain is
    stationary from the first sample.  A non-finite measurement is skipped (predict
    only); before the first finite one the estimate is zero (see :attr:`initialized`).
    """

    def __init__(
        self,
        measurement_std: np.ndarray,
        process_std: np.ndarray,
        dt: float = FRI_CYCLE_NS / 1e9,
        model: Literal["constant", "rate"] = "constant",
    ) -> None:
        r = np.array(measurement_std, dtype=np.float64)
        q = np.array(process_std, dtype=np.float64)
        for name, v in (("measurement_std", r), ("process_std", q)):
            if v.shape != (6,) or not np.all(np.isfinite(v)) or not np.all(v > 0):
                raise ValueError(f"{name} must be 6 finite values > 0, got {v.tolist()!r}")
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a finite time > 0, got {dt!r}")
        if model not in ("constant", "rate"):
            raise ValueError(f"model must be 'constant' or 'rate', got {model!r}")
        # here, not at the top: filterpy imports scipy.stats, 0.5-1.5 s that every service
        # process importing the sensor model paid at start-up for a smoother no run uses
        from filterpy.common import Q_discrete_white_noise
        from filterpy.kalman import KalmanFilter
        from scipy.linalg import block_diag, solve_discrete_are

        self.model = model
        self.dt = float(dt)
        self.measurement_std = r
        self.process_std = q

        if model == "constant":
            dim_x = 6
            F = np.eye(6)
            H = np.eye(6)
            Q = np.diag(q**2)
            self._pos = np.arange(6)
        else:
            dim_x = 12
            F = block_diag(*([np.array([[1.0, dt], [0.0, 1.0]])] * 6))
            H = np.zeros((6, 12))
            H[np.arange(6), 2 * np.arange(6)] = 1.0
            Q = block_diag(*(Q_discrete_white_noise(2, dt=dt, var=qi**2) for qi in q))
            self._pos = 2 * np.arange(6)
        R = np.diag(r**2)
        kf = KalmanFilter(dim_x=dim_x, dim_z=6)
        kf.F, kf.H, kf.Q, kf.R = F, H, Q, R
        # Steady-state prior covariance: the gain is the stationary one from sample 1.
        self._P_ss = solve_discrete_are(F.T, H.T, Q, R)
        kf.P = self._P_ss.copy()
        self._kf = kf
        self._initialized = False
        self._estimate = np.zeros(6)

    @classmethod
    def for_sensor(
        cls,
        config: AtiConfig,
        *,
        model: Literal["constant", "rate"] = "constant",
        tracking_index: float | None = None,
    ) -> WrenchKalmanFilter:
        """Tuned for ``config``: r from noise + quantisation, q from a tracking index.

        ``tracking_index`` is q/r for "constant" (default 0.1) and q·dt²/r for "rate"
        (default 0.01); larger tracks faster and smooths less.
        """
        if model not in ("constant", "rate"):
            raise ValueError(f"model must be 'constant' or 'rate', got {model!r}")
        lam = (0.1 if model == "constant" else 0.01) if tracking_index is None else float(tracking_index)
        if not (math.isfinite(lam) and lam > 0):
            raise ValueError(f"tracking_index must be > 0, got {tracking_index!r}")
        step = config.effective_resolution
        r = np.sqrt(config.noise_std**2 + step**2 / 12.0)
        dt = config.sample_period_s
        q = lam * r if model == "constant" else lam * r / dt**2
        return cls(r, q, dt=dt, model=model)

    @property
    def initialized(self) -> bool:
        return self._initialized

    @property
    def estimate(self) -> np.ndarray:
        """(6,) current filtered wrench."""
        return self._estimate.copy()

    def reset(self) -> None:
        """Forget the state; the next finite measurement restarts the filter."""
        self._kf.x[:] = 0.0
        self._kf.P = self._P_ss.copy()
        self._initialized = False
        self._estimate[:] = 0.0

    def update(self, wrench: np.ndarray) -> np.ndarray:
        """Feed one measured wrench (6,), get the filtered wrench (6,)."""
        z = np.asarray(wrench, dtype=np.float64)
        if z.shape != (6,):
            raise ValueError(f"wrench must have shape (6,), got {z.shape}")
        kf = self._kf
        finite = bool(np.isfinite(z).all())
        if not self._initialized:
            if finite:
                kf.x[:] = 0.0
                kf.x[self._pos, 0] = z
                # Zero residual: leaves x at z and turns P into the steady posterior.
                kf.update(z.reshape(6, 1))
                self._initialized = True
                self._estimate[:] = z
            return self._estimate.copy()
        kf.predict()
        kf.update(z.reshape(6, 1) if finite else None)
        self._estimate[:] = kf.x[self._pos, 0]
        return self._estimate.copy()
