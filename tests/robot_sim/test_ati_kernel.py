"""The compiled ATI sample against the model written out in numpy, one draw per sample:
the same records bit for bit (noise and drift drawn in blocks, saturation, tare, NaN input,
time that goes backwards), and ``sample``'s wrench the record's ``wrench``, bit for bit."""

import math

import numpy as np
import pytest

from robot_sim.ati.sensor import AtiConfig, AtiSensor, _SAT_BITS_ARRAY, _STATUS_NONFINITE, _STATUS_SATURATED


class Reference:
    """AtiSensor.read as plain numpy, drawing 6 normals per sample from each stream."""

    def __init__(self, config, seed):
        noise_ss, drift_ss = np.random.SeedSequence(seed).spawn(2)
        self.noise = np.random.Generator(np.random.PCG64(noise_ss))
        self.drift_rng = np.random.Generator(np.random.PCG64(drift_ss))
        self.c = config
        self.drift = np.zeros(6)
        self.tare = np.zeros(6)
        self.acc = np.zeros(6)
        self.remaining = self.n = 0
        self.t0 = None
        self.last_t = 0
        self.last = np.zeros(6, dtype=np.int32)

    def read(self, x, t):
        if self.t0 is None:
            self.t0 = self.last_t = t
        elif t > self.last_t:
            if np.any(self.c.bias_drift_std > 0):
                self.drift += self.drift_rng.standard_normal(6) * self.c.bias_drift_std * math.sqrt((t - self.last_t) * 1e-9)
            self.last_t = t
        if not np.isfinite(x).all():
            return _STATUS_NONFINITE, self.last.copy()
        raw = x + self.c.bias
        raw += self.drift
        raw += self.noise.standard_normal(6) * self.c.noise_std
        sat = np.abs(raw) > self.c.ranges
        status = 0
        if sat.any():
            status = _STATUS_SATURATED | int(_SAT_BITS_ARRAY[sat].sum())
            if self.c.saturation == "clip":
                raw = np.clip(raw, -self.c.full_scale, self.c.full_scale)
        if self.remaining:
            self.acc += raw
            self.remaining -= 1
            if self.remaining == 0:
                self.tare = self.acc / self.n
        step = np.array(self.c.step_counts, dtype=np.float64)
        v = np.rint((raw - self.tare) * self.c.counts_per_unit / step) * step
        counts = np.clip(v, -(2**31 - 1), 2**31 - 1).astype(np.int32)
        self.last = counts.copy()
        return status, counts


@pytest.mark.parametrize("saturation", ["clip", "flag"])
def test_the_compiled_sample_is_the_numpy_model_bit_for_bit(saturation):
    config = AtiConfig(saturation=saturation)
    sensor, ref = AtiSensor(config, 7), Reference(config, 7)
    rng = np.random.default_rng(1)
    saturated = nonfinite = 0
    for k in range(5000):
        x = rng.normal(size=6) * (500.0 if k % 97 == 0 else 10.0)
        if k % 501 == 0:
            x[2] = np.nan
        t = k * 1_000_000 - (700_000 if k % 13 == 0 else 0)  # now and then a step back in time
        if k in (100, 3000):
            sensor.tare(50)
            ref.tare_n = 50
            ref.remaining = ref.n = 50
            ref.acc[:] = 0.0
        rec, wrench = sensor.sample(x, t) if k % 2 else (sensor.read(x, t), None)
        status, counts = ref.read(x, t)
        assert rec.status == status and np.array_equal(rec.counts, counts) and rec.counts.dtype == np.int32, k
        if wrench is not None:  # the kernel's wrench is the record's, bit for bit, and no zero has a sign
            expected = counts / np.asarray(config.counts_per_unit)
            assert np.array_equal(wrench.view(np.int64), expected.view(np.int64)), k
        saturated += bool(status & _STATUS_SATURATED) and status != _STATUS_NONFINITE
        nonfinite += status == _STATUS_NONFINITE
    assert saturated > 20 and nonfinite == 10  # both paths were exercised
