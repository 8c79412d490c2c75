"""ATI Mini45 / Net F/T model: statistics, quantisation, counts, saturation, sequences,
tare, drift, non-finite input, the Kalman smoother and config validation."""

import math

import numpy as np
import pytest

from robot_sim.ati.filter import WrenchKalmanFilter
from robot_sim.ati.rdt import AtiStatus, RdtRecord, SATURATION_BITS
from robot_sim.ati.sensor import AtiConfig, AtiSensor

MS = 1_000_000  # ns
ZERO6 = np.zeros(6)


def ideal(**overrides):
    """No noise, bias, drift; quantised only at one count -- readings are exact."""
    base = dict(noise_std=ZERO6, bias=ZERO6, bias_drift_std=ZERO6, resolution=ZERO6)
    base.update(overrides)
    return AtiConfig.mini45(**base)


def stream(sensor, wrench, n, t0_ms=0):
    return [sensor.read(wrench, (t0_ms + k) * MS) for k in range(n)]


def wrenches(records, config):
    return np.array([r.wrench(config) for r in records])


# -- statistics at rest ----------------------------------------------------------


def test_zero_load_mean_and_std_match_bias_and_noise():
    bias = np.array([1.5, -0.9, 3.2, 0.04, -0.03, 0.012])
    sigma = np.array([0.06, 0.08, 0.1, 0.002, 0.0025, 0.001])
    cfg = ideal(bias=bias, noise_std=sigma)
    n = 20_000
    w = wrenches(stream(AtiSensor(cfg, seed=7), ZERO6, n), cfg)
    # 5 standard errors of each estimator: mean se = σ/√n, std se ≈ σ/√(2n).
    assert np.all(np.abs(w.mean(0) - bias) < 5 * sigma / math.sqrt(n))
    assert np.all(np.abs(w.std(0, ddof=1) - sigma) < 5 * sigma / math.sqrt(2 * n))


def test_noise_stream_does_not_depend_on_drift():
    # Same seed with and without drift: the difference is the drift alone, a smooth
    # random walk, so its one-step increments are far below the noise.
    base = dict(bias=ZERO6, resolution=ZERO6)
    off = AtiConfig.mini45(bias_drift_std=ZERO6, **base)
    on = AtiConfig.mini45(**base)
    a = wrenches(stream(AtiSensor(off, 3), ZERO6, 2000), off)
    b = wrenches(stream(AtiSensor(on, 3), ZERO6, 2000), on)
    step_std = np.diff(b - a, axis=0).std(0)
    expected = on.bias_drift_std * math.sqrt(1e-3)
    assert np.all(step_std < 2 * expected + 2e-6)  # + rounding to one count
    # Had the noise streams differed, the increments would be ~√2 σ_noise, 100× larger.
    assert np.all(step_std < 0.05 * on.noise_std)
    # And the difference stays within a random walk's reach over the 2 s run.
    assert np.all(np.abs(b - a).max(0) < 5 * on.bias_drift_std * math.sqrt(2.0))


# -- quantisation, counts, wire format -------------------------------------------


def test_outputs_are_multiples_of_the_resolution(rng):
    cfg = AtiConfig.mini45()
    sensor = AtiSensor(cfg, seed=11)
    records = []
    for k in range(3000):
        if k == 1000:
            sensor.tare(17)
        records.append(sensor.read(rng.uniform(-0.8, 0.8, 6) * cfg.ranges, k * MS))
    counts = np.array([r.counts for r in records], dtype=np.int64)
    step = cfg.step_counts.astype(np.int64)
    assert np.array_equal(step, [125_000, 125_000, 125_000, 2660, 2660, 1330])
    assert np.all(counts % step == 0)
    q = wrenches(records, cfg) / cfg.effective_resolution
    assert np.allclose(q, np.rint(q), atol=1e-9)
    # Not trivially constant: quantised values really vary.
    assert all(len(np.unique(counts[:, i])) > 50 for i in range(6))


def test_counts_round_trip_to_newtons_and_newton_metres():
    true = np.array([10.0, -20.5, 100.25, 1.0, -0.5, 0.25])
    cfg = ideal()
    rec = AtiSensor(cfg, seed=0).read(true, 0)
    assert rec.counts.dtype == np.int32
    assert rec.counts.tolist() == [10_000_000, -20_500_000, 100_250_000, 1_000_000, -500_000, 250_000]
    assert np.allclose(rec.wrench(cfg), true, rtol=0, atol=1e-12)

    coarse = ideal(counts_per_force=1000, counts_per_torque=100_000)
    rec = AtiSensor(coarse, seed=0).read(true, 0)
    assert rec.counts.tolist() == [10_000, -20_500, 100_250, 100_000, -50_000, 25_000]
    assert np.allclose(rec.wrench(coarse), true, rtol=0, atol=1e-12)
    # Reading it with another calibration gives another wrench: the scale matters.
    assert not np.allclose(rec.wrench(cfg), true)


def test_rdt_record_wire_round_trip():
    rec = RdtRecord(2**32 - 1, 7, int(AtiStatus.ERROR | AtiStatus.SAT_FZ), np.array([-1, 2, -(2**31 - 1), 4, 5, 2**31 - 1], dtype=np.int32))
    data = rec.pack()
    assert len(data) == RdtRecord.SIZE == 36
    assert data[:4] == b"\xff\xff\xff\xff"  # big-endian, as on the wire
    assert RdtRecord.unpack(data) == rec
    with pytest.raises(ValueError, match="36 bytes"):
        RdtRecord.unpack(data[:-1])
    with pytest.raises(ValueError, match="rdt_sequence"):
        RdtRecord(2**32, 0, 0, np.zeros(6, dtype=np.int32))
    with pytest.raises(ValueError, match="counts"):
        RdtRecord(0, 0, 0, np.zeros(6))


# -- saturation ------------------------------------------------------------------


@pytest.mark.parametrize("axis", range(6))
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_saturation_clips_at_the_range_sets_the_bit_and_clears(axis, sign):
    cfg = ideal(resolution=AtiConfig.mini45().resolution)
    sensor = AtiSensor(cfg, seed=1)
    over = np.zeros(6)
    over[axis] = sign * 1.5 * cfg.ranges[axis]
    rec = sensor.read(over, 0)
    w = rec.wrench(cfg)
    step = cfg.effective_resolution[axis]
    assert abs(w[axis]) <= cfg.ranges[axis]
    assert abs(w[axis]) > cfg.ranges[axis] - step
    assert np.sign(w[axis]) == sign
    assert w[axis] == pytest.approx(sign * cfg.full_scale[axis], abs=1e-12)
    flags = rec.flags()
    assert SATURATION_BITS[axis] in flags
    assert AtiStatus.FT_OUT_OF_RANGE in flags and AtiStatus.ERROR in flags
    assert all(b not in flags for i, b in enumerate(SATURATION_BITS) if i != axis)
    assert not rec.ok

    back = np.zeros(6)
    back[axis] = sign * 0.5 * cfg.ranges[axis]
    rec = sensor.read(back, MS)
    assert rec.status == 0 and rec.ok
    assert rec.wrench(cfg)[axis] == pytest.approx(back[axis], abs=step)


def test_in_range_load_is_not_flagged():
    cfg = ideal()
    rec = AtiSensor(cfg, seed=1).read(0.999 * cfg.ranges * np.array([1, -1, 1, -1, 1, -1]), 0)
    assert rec.status == 0


def test_flag_mode_reports_beyond_the_range_but_flags_it():
    cfg = ideal(saturation="flag")
    rec = AtiSensor(cfg, seed=1).read(np.array([400.0, 0, -700, 0, 0, 12]), 0)
    assert np.allclose(rec.wrench(cfg), [400, 0, -700, 0, 0, 12])
    assert rec.flags() == (
        AtiStatus.ERROR | AtiStatus.FT_OUT_OF_RANGE | AtiStatus.SAT_FX | AtiStatus.SAT_FZ | AtiStatus.SAT_TZ
    )


# -- sequences -------------------------------------------------------------------


def test_sequences_start_at_one_and_increment_per_record():
    recs = stream(AtiSensor(ideal(), 0), ZERO6, 5)
    assert [r.rdt_sequence for r in recs] == [1, 2, 3, 4, 5]
    assert [r.ft_sequence for r in recs] == [1, 2, 3, 4, 5]


def test_sequences_wrap_at_2_to_the_32():
    start = 2**32 - 2
    sensor = AtiSensor(ideal(), 0, rdt_sequence_start=start, ft_sequence_start=start)
    recs = stream(sensor, ZERO6, 4)
    expected = [2**32 - 2, 2**32 - 1, 0, 1]
    assert [r.rdt_sequence for r in recs] == expected
    assert [r.ft_sequence for r in recs] == expected
    # The wrapped record still packs as a uint32.
    assert RdtRecord.unpack(recs[2].pack()).rdt_sequence == 0


def test_ft_sequence_counts_internal_samples_not_records():
    sensor = AtiSensor(ideal(), 0)
    times_ms = [0, 2, 4, 4, 5, 5.5, 9]  # RDT slower than the ADC, a repeat, a partial period
    recs = [sensor.read(ZERO6, int(t * MS)) for t in times_ms]
    assert [r.rdt_sequence for r in recs] == [1, 2, 3, 4, 5, 6, 7]
    assert [r.ft_sequence for r in recs] == [1, 3, 5, 5, 6, 6, 10]
    # A clock that goes backwards does not rewind ft_sequence.
    assert sensor.read(ZERO6, 3 * MS).ft_sequence == 10


# -- determinism -----------------------------------------------------------------


def test_same_seed_same_records_different_seed_different(rng):
    cfg = AtiConfig.mini45()
    loads = rng.uniform(-50, 50, (500, 6)) * np.array([1, 1, 1, 0.01, 0.01, 0.01])

    def run(seed):
        sensor = AtiSensor(cfg, seed)
        out = []
        for k, w in enumerate(loads):
            if k == 100:
                sensor.tare(10)
            out.append(sensor.read(w, k * MS))
        return out

    a, b, c = run(42), run(42), run(43)
    assert a == b
    assert a != c
    diff = np.array([x.counts != y.counts for x, y in zip(a, c)])
    assert diff.mean() > 0.3


# -- tare ------------------------------------------------------------------------


def test_tare_of_one_sample_zeroes_that_record():
    cfg = AtiConfig.mini45(bias_drift_std=ZERO6)
    sensor = AtiSensor(cfg, 5)
    before = stream(sensor, ZERO6, 10)
    assert np.all(np.abs(wrenches(before, cfg).mean(0)) > 0.5 * np.abs(cfg.bias))
    sensor.tare()
    assert sensor.tare_pending
    rec = sensor.read(ZERO6, 10 * MS)
    assert rec.counts.tolist() == [0] * 6
    assert not sensor.tare_pending


def test_tare_removes_the_bias():
    cfg = AtiConfig.mini45(bias_drift_std=ZERO6, resolution=ZERO6)
    sigma = cfg.noise_std
    sensor = AtiSensor(cfg, 9)
    stream(sensor, ZERO6, 50)
    n_tare, n = 200, 10_000
    sensor.tare(n_tare)
    stream(sensor, ZERO6, n_tare, t0_ms=50)
    assert np.all(np.abs(sensor.tare_offset - cfg.bias) < 5 * sigma / math.sqrt(n_tare))
    w = wrenches(stream(sensor, ZERO6, n, t0_ms=50 + n_tare), cfg)
    # The tare carries σ/√n_tare of error; the mean estimate σ/√n on top of it.
    bound = 5 * sigma * math.sqrt(1 / n_tare + 1 / n)
    assert np.all(np.abs(w.mean(0)) < bound)
    assert np.all(np.abs(w.mean(0)) < 0.05 * np.abs(cfg.bias))


def test_tare_removes_a_static_load_and_clear_tare_restores_it():
    cfg = ideal(bias=np.array([2.0, 0, 0, 0, 0.05, 0]))
    sensor = AtiSensor(cfg, 0)
    tool = np.array([0.0, 0.0, -20.0, 0.3, 0.0, 0.0])  # tool weight hanging on the sensor
    sensor.tare(3)
    stream(sensor, tool, 3)
    assert np.allclose(sensor.read(tool, 3 * MS).wrench(cfg), 0, atol=1e-6)
    extra = np.array([0, 0, -10.0, 0, 0, 0])
    assert np.allclose(sensor.read(tool + extra, 4 * MS).wrench(cfg), extra, atol=1e-6)
    sensor.clear_tare()
    assert np.allclose(sensor.read(tool, 5 * MS).wrench(cfg), tool + cfg.bias, atol=1e-6)


def test_tare_argument_is_validated():
    sensor = AtiSensor(ideal(), 0)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="n_samples"):
            sensor.tare(bad)


# -- drift -----------------------------------------------------------------------


def test_drift_is_a_random_walk_with_linear_variance():
    sigma_d = np.array([0.02, 0.02, 0.03, 4e-4, 4e-4, 2e-4])
    cfg = ideal(bias_drift_std=sigma_d)
    m, period_ms, t1, t2 = 300, 10, 1.0, 4.0
    d1, d2 = np.empty((m, 6)), np.empty((m, 6))
    for s in range(m):
        sensor = AtiSensor(cfg, seed=1000 + s)
        for k in range(int(t2 * 1000 / period_ms) + 1):
            t_ms = k * period_ms
            w = sensor.read(ZERO6, t_ms * MS).wrench(cfg)
            if t_ms == t1 * 1000:
                d1[s] = w
        d2[s] = w
    var1, var2 = d1.var(0, ddof=1) / sigma_d**2, d2.var(0, ddof=1) / sigma_d**2
    # Relative std of a variance estimate from m samples is √(2/(m-1)) ≈ 0.08; 5 of those.
    tol = 5 * math.sqrt(2 / (m - 1))
    assert np.all(np.abs(var1 / t1 - 1) < tol)
    assert np.all(np.abs(var2 / t2 - 1) < tol)
    ratio = var2 / var1
    assert np.all((ratio > 2.5) & (ratio < 6.0))
    # Independent increments: Var(d(t2) - d(t1)) = σ²(t2 - t1).
    assert np.all(np.abs((d2 - d1).var(0, ddof=1) / sigma_d**2 / (t2 - t1) - 1) < tol)
    # It is drift, not noise: a single run moves smoothly.
    assert np.all(np.abs(d1.mean(0)) < 5 * sigma_d * math.sqrt(t1 / m))


# -- non-finite input ------------------------------------------------------------


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_input_sets_the_error_bit_and_holds_the_last_good_value(bad):
    cfg = AtiConfig.mini45()
    sensor = AtiSensor(cfg, 2)
    good = sensor.read(np.array([5.0, 1, -3, 0.1, 0, 0.2]), 0)
    broken = np.array([1.0, bad, 0, 0, 0, 0])
    rec = sensor.read(broken, MS)
    assert rec.flags() == AtiStatus.ERROR | AtiStatus.INPUT_NONFINITE
    assert rec.counts.dtype == np.int32
    assert np.array_equal(rec.counts, good.counts)
    assert np.all(np.isfinite(rec.wrench(cfg)))
    assert rec.rdt_sequence == good.rdt_sequence + 1 and rec.ft_sequence == good.ft_sequence + 1
    again = sensor.read(np.full(6, bad), 2 * MS)
    assert np.array_equal(again.counts, good.counts) and not again.ok
    assert sensor.read(np.zeros(6), 3 * MS).status == 0


def test_non_finite_first_record_reports_zero_and_is_skipped_by_tare():
    cfg = ideal(bias=np.array([1.0, 0, 0, 0, 0, 0]))
    sensor = AtiSensor(cfg, 0)
    sensor.tare(2)
    rec = sensor.read(np.full(6, np.nan), 0)
    assert rec.counts.tolist() == [0] * 6 and AtiStatus.INPUT_NONFINITE in rec.flags()
    assert sensor.tare_pending
    stream(sensor, ZERO6, 2, t0_ms=1)
    assert np.allclose(sensor.tare_offset, cfg.bias)


def test_wrongly_shaped_input_is_a_clear_error():
    with pytest.raises(ValueError, match=r"shape \(6,\)"):
        AtiSensor(ideal(), 0).read(np.zeros(3), 0)
    with pytest.raises(ValueError, match="seed"):
        AtiSensor(ideal(), -1)
    with pytest.raises(TypeError, match="AtiConfig"):
        AtiSensor({"ranges": 1}, 0)


# -- Kalman smoother -------------------------------------------------------------


def _kf_run(model, seed=4):
    cfg = AtiConfig.mini45(bias_drift_std=ZERO6)
    sensor = AtiSensor(cfg, seed)
    kf = WrenchKalmanFilter.for_sensor(cfg, model=model)
    step = np.array([0.0, -30.0, 50.0, 2.0, 0.0, -0.5])
    raw, out = [], []
    for k in range(6000):
        z = sensor.read(ZERO6 if k < 3000 else step, k * MS).wrench(cfg)
        raw.append(z)
        out.append(kf.update(z))
    return cfg, step, np.array(raw), np.array(out)


@pytest.mark.parametrize("model, factor", [("constant", 3.5), ("rate", 2.5)])
def test_kalman_reduces_the_noise_on_a_constant_wrench(model, factor):
    _, _, raw, out = _kf_run(model)
    ratio = raw[500:3000].std(0) / out[500:3000].std(0)
    assert np.all(ratio > factor), ratio


@pytest.mark.parametrize("model, within", [("constant", 40), ("rate", 60)])
def test_kalman_tracks_a_step(model, within):
    cfg, step, raw, out = _kf_run(model)
    before = out[2999]
    after = out[3000 + within :]
    moved = np.abs(step) > 0
    # Every later estimate is within 5 % of the step (plus the noise floor) of the new level.
    err = np.abs(after[:, moved] - (raw[3500:].mean(0))[moved])
    assert np.all(err < 0.05 * np.abs(step[moved]) + 3 * cfg.noise_std[moved])
    # ...and the filter had not already been there before the step.
    assert np.all(np.abs(before[moved] - step[moved]) > 0.5 * np.abs(step[moved]))


def test_kalman_skips_non_finite_measurements_and_validates():
    kf = WrenchKalmanFilter.for_sensor(AtiConfig.mini45())
    assert not kf.initialized
    assert np.array_equal(kf.update(np.full(6, np.nan)), ZERO6)
    first = np.arange(6.0)
    assert np.allclose(kf.update(first), first)
    assert kf.initialized
    held = kf.update(np.array([np.nan, 0, 0, 0, 0, 0]))
    assert np.all(np.isfinite(held)) and np.allclose(held, first)
    kf.reset()
    assert not kf.initialized
    with pytest.raises(ValueError, match="measurement_std"):
        WrenchKalmanFilter(np.zeros(6), np.ones(6))
    with pytest.raises(ValueError, match="process_std"):
        WrenchKalmanFilter(np.ones(6), np.ones(5))
    with pytest.raises(ValueError, match="model"):
        WrenchKalmanFilter(np.ones(6), np.ones(6), model="jerk")
    with pytest.raises(ValueError, match="shape"):
        kf.update(np.zeros(7))


# -- configuration ---------------------------------------------------------------


def test_mini45_defaults_are_the_thesis_sensor():
    cfg = AtiConfig.mini45()
    assert cfg == AtiConfig()
    assert cfg.ranges.tolist() == [290, 290, 580, 10, 10, 10]
    assert (cfg.counts_per_force, cfg.counts_per_torque) == (1_000_000, 1_000_000)
    assert cfg.sample_period_ns == 1_000_000
    assert cfg.saturation == "clip"
    assert hash(cfg) == hash(AtiConfig.mini45())
    assert cfg != AtiConfig.mini45(saturation="flag")
    with pytest.raises(ValueError):
        cfg.ranges[0] = 1.0  # read-only: the frozen config cannot be changed through its arrays


@pytest.mark.parametrize(
    "field, value",
    [
        ("ranges", [290, 290, 580, 10, 10]),
        ("ranges", [290, 290, 580, 10, 10, 0]),
        ("ranges", [290, 290, np.nan, 10, 10, 10]),
        ("ranges", "big"),
        ("counts_per_force", 0),
        ("counts_per_force", 1.5),
        ("counts_per_force", 10_000_000),  # 580 N overflows int32
        ("counts_per_torque", 10**9),  # 10 Nm overflows int32
        ("resolution", [-0.1, 0, 0, 0, 0, 0]),
        ("resolution", [1e-9, 0, 0, 0, 0, 0]),  # finer than one count
        ("resolution", [300, 0, 0, 0, 0, 0]),
        ("noise_std", [0.1, 0.1, -0.1, 0, 0, 0]),
        ("noise_std", [np.inf, 0, 0, 0, 0, 0]),
        ("bias", [0, 0, 600, 0, 0, 0]),
        ("bias_drift_std", [0, 0, 0, -1e-4, 0, 0]),
        ("sample_period_s", 0.0),
        ("sample_period_s", -1e-3),
        ("sample_period_s", float("nan")),
        ("saturation", "wrap"),
    ],
)
def test_bad_config_raises_naming_the_field(field, value):
    with pytest.raises(ValueError, match=f"AtiConfig.{field}") as err:
        AtiConfig.mini45(**{field: value})
    if not isinstance(value, (list, str)) or field == "saturation":
        assert repr(value) in str(err.value) or str(value) in str(err.value)
