"""Model of an ATI Mini45 (Gamma class) force/torque sensor streaming RDT records.

The physics gives the TRUE wrench acting on the sensor; :class:`AtiSensor` returns
what an ATI Net F/T box would put on the wire for it, one RDT record per call, at
1 kHz next to the simulation.  :class:`WrenchKalmanFilter` is an optional smoother
for consumers that want a filtered wrench.

Axis order everywhere: ``Fx, Fy, Fz, Tx, Ty, Tz`` (N and Nm), sensor frame.

Figures and where they come from
--------------------------------
* Ranges ±290 N (Fx, Fy), ±580 N (Fz), ±10 Nm (Tx, Ty, Tz): the thesis, section 5
  ("The ATI Multi-Axis Force/Torque Sensor ... up to 290 N in x and y ..., 580 N in
  the z-direction ... and up to 10 Nm", its ref. [44]); this is ATI's Mini45
  calibration ``SI-290-10`` (the calibration name also appears in the ATI EtherCAT
  F/T log in nasa-jpl/fastcat's device documentation).
* Counts per force 1 000 000 counts/N, counts per torque 1 000 000 counts/Nm:
  ATI's Ethernet Axia manual (doc. 9610-05-Ethernet Axia-09, "cpf  Counts per Force
  ... 1000000", and its Demo CSV section: "divide all force values by this number")
  and an ATI EtherCAT F/T with calibration SI-290-10 reporting
  ``counts_per_force: 1000000``, ``counts_per_torque: 1000000`` in N and N-m
  (nasa-jpl/fastcat docs).  With these, ±580 N is 5.8e8 counts, inside int32.
  (ros-drivers/ati_netft_ros_driver hard-codes 1e9 counts per torque unit; at
  counts/Nm that would overflow int32 above 2.1 Nm, so it is not used here.)
* RDT record: 36 bytes, big-endian ``uint32 rdt_sequence, uint32 ft_sequence,
  uint32 status, int32 Fx, Fy, Fz, Tx, Ty, Tz`` (ros-drivers/ati_netft_ros_driver,
  ``netft_rdt_driver.cpp``).  ``rdt_sequence`` starts at 1 and increments with every
  record sent, a gap means lost packets; ``ft_sequence`` increments with every new
  F/T measurement (ATI Net F/T manual 9620-05-net ft-11, table 5.1; Ethernet Axia
  manual table 7.1).  RDT streams at up to 7 kHz (DESIGN.md); here one record per
  1 ms sample by default.
* Resolution (quantisation step) 1/8 N (Fx, Fy, Fz), 1/376 Nm (Tx, Ty), 1/752 Nm
  (Tz): ATI's published Mini45 table for calibration SI-290-10 with a Net F/T /
  16-bit DAQ system.  NOTE: recalled from ATI's product page, which is not in this
  project's reference corpus.  The one written source found is second-hand: a
  component summary compiled from that page gives, for the larger Mini45
  calibration SI-580-20 (twice the ranges), 0.25 N on every force axis and
  "0.003-0.005 Nm" on the torques.  Halved, 0.25 N is our 1/8 N; the torque
  figures fit 1/376 and 1/188 Nm (0.0027, 0.0053) rounded, which halve to our
  1/752 and 1/376 Nm.  So the force step agrees and the torque steps agree to the
  summary's rounding; check them against a real sensor's calibration certificate
  before trusting the third significant figure.  The step is
  snapped to whole counts (1/376 Nm -> 2660 counts), see
  :attr:`AtiConfig.effective_resolution`.
* White noise std, half the resolution (1/16 N, 1/752 Nm, 1/1504 Nm): ASSUMPTION.
  ATI does not publish a noise figure for the Mini45; it defines resolution as the
  smallest detectable change, which for a strain-gauge system is set by its noise
  floor, so σ = resolution / 2 keeps readings flickering over 2–3 steps at rest as
  real unfiltered Net F/T data does.
* Initial bias (1.5, -0.9, 3.2) N, (0.04, -0.03, 0.012) Nm: ILLUSTRATIVE.  An
  un-biased sensor reads a few N of offset (tool mass, mounting stress); the values
  only make tare necessary.  Set to zero for an ideal sensor.
* Bias drift 0.02/0.02/0.03 N/√s, 4e-4/4e-4/2e-4 Nm/√s (random walk): ASSUMPTION,
  thermal drift of strain gauges; gives ~0.15 N after a one-minute demonstration.

Status word (uint32)
--------------------
The layout of the upper bits follows ATI's system status code (Ethernet Axia manual,
tables 4.7/4.9: bit 31 "any error", bit 30 "F/T out of range", 0xC0000000 for an
out-of-range load); as on the real sensor, any error bit also sets bit 31, so
``status != 0`` means "do not trust this record".  Bits 8-14 are in the range ATI
marks reserved and are specific to this model:

=====  ======================  ==============================================
bit    :class:`AtiStatus`      meaning
=====  ======================  ==============================================
8-13   SAT_FX ... SAT_TZ       that axis exceeded its range in this record
14     INPUT_NONFINITE         the true wrench had a NaN/inf (broken physics
                               step); the counts repeat the last good record
30     FT_OUT_OF_RANGE         at least one axis saturated
31     ERROR                   any of the above
=====  ======================  ==============================================

Bits describe the record they are in; they are not latched (they clear as soon as
the load is back in range).  Latching, as the ROS driver does, is the consumer's
choice.  ATI's own out-of-range test combines axes (a percentage of the calibrated
ranges over 105 %); this model tests each axis against its range.

Measurement model (one :meth:`AtiSensor.read`)
----------------------------------------------
``raw = true + bias + drift(t) + noise``; drift is a random walk advanced by the
elapsed sim time since the previous read (variance ``drift_std² · Δt``).  If
``|raw_i| > range_i`` the axis saturates: with ``saturation="clip"`` it is clipped
to full scale (the largest multiple of the step within the range) and flagged;
with ``"flag"`` it is only flagged (the sensor keeps reporting beyond the rated
range).  Then ``value = raw - tare``, quantised to the step, converted to int32
counts.  Saturation is judged on the raw signal because that is what the gauges
see; a tared reading can therefore sit below full scale while saturated.

Tare (ATI's software bias command)
----------------------------------
``tare(n_samples=1)`` arms a tare: the raw readings (after saturation, before the
old tare) of the next ``n_samples`` finite records are averaged and that mean becomes
the offset subtracted from every later reading, starting with the record that
completes the average (so with ``n_samples=1`` that record reads exactly 0, like the
Net F/T's bias of the current reading).  The tare therefore removes whatever is
present then: bias, accumulated drift, and any load (e.g. the tool's weight, which
is how tare is used in practice) -- and carries the noise of its average
(σ/√n).  Drift after the tare is not removed.  ``clear_tare()`` drops it.

Non-finite input
----------------
A NaN or inf in the true wrench never reaches the counts: the record repeats the
counts of the last record made from a finite input (zeros before the first one)
with ``ERROR | INPUT_NONFINITE`` set.  Sequences still advance (a record is sent),
drift still advances, a pending tare ignores the record.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numba import njit

from kernel_plumbing.addresses import JIT, HoldsAddresses, address, addresses, carray_at, entry
from robot_sim.ati.rdt import INT32_MAX, SATURATION_BITS, UINT32_MASK, AtiStatus, RdtRecord
from robot_sim.cycle import FRI_CYCLE_NS

__all__ = [
    "AXES",
    "AtiConfig",
    "AtiSensor",
    "AtiStatus",
    "RdtRecord",
    "SATURATION_BITS",
]

AXES: tuple[str, ...] = ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")

MINI45_RANGES = (290.0, 290.0, 580.0, 10.0, 10.0, 10.0)
MINI45_RESOLUTION = (1 / 8, 1 / 8, 1 / 8, 1 / 376, 1 / 376, 1 / 752)
MINI45_NOISE_STD = tuple(r / 2 for r in MINI45_RESOLUTION)
MINI45_BIAS = (1.5, -0.9, 3.2, 0.04, -0.03, 0.012)
MINI45_DRIFT_STD = (0.02, 0.02, 0.03, 4e-4, 4e-4, 2e-4)


_SAT_BITS_ARRAY = np.array([int(b) for b in SATURATION_BITS], dtype=np.int64)
_STATUS_SATURATED = int(AtiStatus.ERROR | AtiStatus.FT_OUT_OF_RANGE)
_STATUS_NONFINITE = int(AtiStatus.ERROR | AtiStatus.INPUT_NONFINITE)
_STATUS_SATURATED_K = np.int64(_STATUS_SATURATED)  # constants the compiled sample kernel reads
_INT32_MAX_F = float(INT32_MAX)


def _vec6(name: str, value: Any, *, positive: bool = False, nonnegative: bool = False) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"AtiConfig.{name} must be 6 numbers, got {value!r}") from None
    if arr.shape != (6,):
        raise ValueError(f"AtiConfig.{name} must have shape (6,), got shape {arr.shape}: {value!r}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"AtiConfig.{name} must be finite, got {value!r}")
    if positive and not np.all(arr > 0):
        raise ValueError(f"AtiConfig.{name} must be > 0 on every axis, got {value!r}")
    if nonnegative and not np.all(arr >= 0):
        raise ValueError(f"AtiConfig.{name} must be >= 0 on every axis, got {value!r}")
    # Read-only so a frozen config really is frozen (arrays are otherwise mutable).
    arr.flags.writeable = False
    return arr


def _check_int(name: str, value: Any, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"AtiConfig.{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


@dataclass(frozen=True, eq=False)
class AtiConfig:
    """Static description of one sensor + Net F/T calibration.  Defaults: Mini45 SI-290-10.

    Array fields are stored as read-only float64 arrays of shape (6,), order
    Fx, Fy, Fz, Tx, Ty, Tz.  Invalid values raise ``ValueError`` naming the field.
    """

    ranges: np.ndarray = field(default_factory=lambda: np.array(MINI45_RANGES))
    """Rated range ±ranges (N, Nm); beyond it the axis saturates."""
    counts_per_force: int = 1_000_000
    counts_per_torque: int = 1_000_000
    resolution: np.ndarray = field(default_factory=lambda: np.array(MINI45_RESOLUTION))
    """Quantisation step (N, Nm); 0 means one count (no coarser quantisation)."""
    noise_std: np.ndarray = field(default_factory=lambda: np.array(MINI45_NOISE_STD))
    """Std of the white noise added to every sample (N, Nm)."""
    bias: np.ndarray = field(default_factory=lambda: np.array(MINI45_BIAS))
    """Offset at the first reading (N, Nm), before any tare."""
    bias_drift_std: np.ndarray = field(default_factory=lambda: np.array(MINI45_DRIFT_STD))
    """Random-walk intensity of the offset (N/√s, Nm/√s); 0 disables drift."""
    sample_period_s: float = FRI_CYCLE_NS / 1e9
    """Period of the sensor's internal F/T samples (ft_sequence increments): one robot
    cycle by default, the rate the cell samples it at."""
    saturation: Literal["clip", "flag"] = "clip"
    """'clip': saturated axes read full scale; 'flag': they keep the raw value."""

    def __post_init__(self) -> None:
        ranges = _vec6("ranges", self.ranges, positive=True)
        object.__setattr__(self, "ranges", ranges)
        cpf = _check_int("counts_per_force", self.counts_per_force, 1)
        cpt = _check_int("counts_per_torque", self.counts_per_torque, 1)
        object.__setattr__(self, "counts_per_force", cpf)
        object.__setattr__(self, "counts_per_torque", cpt)
        cpu = np.array([cpf] * 3 + [cpt] * 3, dtype=np.float64)
        full_range_counts = ranges * cpu
        if np.any(full_range_counts > INT32_MAX):
            name = "counts_per_force" if np.any(full_range_counts[:3] > INT32_MAX) else "counts_per_torque"
            raise ValueError(
                f"AtiConfig.{name} = {getattr(self, name)!r} makes the range "
                f"{ranges.tolist()!r} overflow int32 counts"
            )

        resolution = _vec6("resolution", self.resolution, nonnegative=True)
        object.__setattr__(self, "resolution", resolution)
        step_f = resolution * cpu
        if np.any((resolution > 0) & (step_f < 0.5)):
            raise ValueError(
                f"AtiConfig.resolution {self.resolution.tolist()!r} is finer than one count "
                "at these counts_per_force/counts_per_torque"
            )
        if np.any(resolution >= ranges):
            raise ValueError(
                f"AtiConfig.resolution {resolution.tolist()!r} must be below the ranges {ranges.tolist()!r}"
            )
        step = np.where(resolution > 0, np.maximum(np.rint(step_f), 1.0), 1.0)

        object.__setattr__(self, "noise_std", _vec6("noise_std", self.noise_std, nonnegative=True))
        bias = _vec6("bias", self.bias)
        if np.any(np.abs(bias) >= ranges):
            raise ValueError(f"AtiConfig.bias {bias.tolist()!r} must lie inside the ranges {ranges.tolist()!r}")
        object.__setattr__(self, "bias", bias)
        object.__setattr__(
            self, "bias_drift_std", _vec6("bias_drift_std", self.bias_drift_std, nonnegative=True)
        )

        period = self.sample_period_s
        if (
            isinstance(period, bool)
            or not isinstance(period, (int, float, np.floating, np.integer))
            or not math.isfinite(period)
            or round(period * 1e9) < 1
        ):
            raise ValueError(f"AtiConfig.sample_period_s must be a finite time >= 1 ns, got {period!r}")
        object.__setattr__(self, "sample_period_s", float(period))
        if self.saturation not in ("clip", "flag"):
            raise ValueError(f"AtiConfig.saturation must be 'clip' or 'flag', got {self.saturation!r}")

        # Derived values, computed once because read() runs at 1 kHz.
        cpu.flags.writeable = False
        step.flags.writeable = False
        full_scale = np.floor(full_range_counts / step) * step / cpu
        full_scale.flags.writeable = False
        object.__setattr__(self, "_cpu", cpu)
        object.__setattr__(self, "_step", step)
        object.__setattr__(self, "_full_scale", full_scale)

    @classmethod
    def mini45(cls, **overrides: Any) -> AtiConfig:
        """The thesis' sensor (Mini45, SI-290-10, Net F/T defaults), fields overridable."""
        return cls(**overrides)

    @property
    def counts_per_unit(self) -> np.ndarray:
        """(6,) counts per N (forces) and per Nm (torques)."""
        return self._cpu  # type: ignore[attr-defined]

    @property
    def step_counts(self) -> np.ndarray:
        """(6,) quantisation step in counts (float64 holding whole numbers)."""
        return self._step  # type: ignore[attr-defined]

    @property
    def effective_resolution(self) -> np.ndarray:
        """(6,) the step actually used, in N / Nm: resolution snapped to whole counts."""
        return self._step / self._cpu  # type: ignore[attr-defined]

    @property
    def full_scale(self) -> np.ndarray:
        """(6,) what a clipped axis reads: the largest multiple of the step within the range."""
        return self._full_scale  # type: ignore[attr-defined]

    @property
    def sample_period_ns(self) -> int:
        return int(round(self.sample_period_s * 1e9))

    def _key(self) -> tuple:
        return tuple(
            tuple(v.tolist()) if isinstance(v, np.ndarray) else v
            for v in (getattr(self, f.name) for f in dataclasses.fields(self))
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, AtiConfig):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())


_BLOCK = 1024  # normals drawn per block: the same stream as one draw of 6 per sample, fewer calls



# rows of AtiSensor._const: what the compiled sample kernel reads, in one array
_BIAS, _NOISE_STD, _RANGE, _FULL_SCALE, _CPU, _STEP, _DRIFT_STD, _SAT_BIT = range(8)
# rows of AtiSensor._state
_DRIFT, _TARE, _TARE_ACC = range(3)


@njit(**JIT)
def _sample_at(x_at, const_at, state_at, tare_at, noise_at, ni, drift_at, di, drift_scale, clip,
               out_at):  # pragma: no cover - compiled
    """One sample: the offset's drift (a step of ``drift_scale`` = sqrt(dt) when time
    advanced), raw = x + bias + drift + noise * std, saturation, tare, quantisation; the
    same operations in the same order as the numpy version had.  ``tare`` = [samples
    still to average, samples in the average].  Writes ``out`` = [counts (whole numbers,
    as float64); the wrench, counts / counts-per-unit; the counts again, kept as the last
    finite sample's] and returns the status word, or -1 for a non-finite ``x`` (then only
    the drift has stepped: the noise is not drawn, the last counts stay).
    By address (kernel_plumbing.addresses): with arrays it cost more than the sample."""
    const, state, tare = carray_at(const_at, (8, 6)), carray_at(state_at, (3, 6)), carray_at(tare_at, (2,))
    x, out = carray_at(x_at, (6,)), carray_at(out_at, (3, 6))
    if drift_scale > 0.0:
        drift_noise = carray_at(drift_at, (di + 1, 6))
        for i in range(6):
            d = drift_noise[di, i] * const[_DRIFT_STD, i]
            d *= drift_scale
            state[_DRIFT, i] += d
    for i in range(6):
        if not np.isfinite(x[i]):
            return -1
    noise = carray_at(noise_at, (ni + 1, 6))
    raw = np.empty(6)
    status = 0
    saturated = False
    for i in range(6):
        r = x[i] + const[_BIAS, i]
        r += state[_DRIFT, i]
        r += noise[ni, i] * const[_NOISE_STD, i]
        if abs(r) > const[_RANGE, i]:
            saturated = True
            status |= np.int64(const[_SAT_BIT, i])
        raw[i] = r
    if saturated:
        status |= _STATUS_SATURATED_K
        if clip:
            for i in range(6):
                raw[i] = min(max(raw[i], -const[_FULL_SCALE, i]), const[_FULL_SCALE, i])
    if tare[0] > 0:
        for i in range(6):
            state[_TARE_ACC, i] += raw[i]
        tare[0] -= 1
        if tare[0] == 0:
            for i in range(6):
                state[_TARE, i] = state[_TARE_ACC, i] / tare[1]
    for i in range(6):
        v = raw[i] - state[_TARE, i]
        v *= const[_CPU, i]
        v /= const[_STEP, i]
        v = np.rint(v)
        v *= const[_STEP, i]
        v = min(max(v, -_INT32_MAX_F), _INT32_MAX_F)
        if v == 0.0:
            v = 0.0  # -0.0 rounded: an int32 count has no sign of zero, nor has its wrench
        out[0, i] = v
        # int32 counts to float64 and divided: what counts / counts_per_unit gives
        out[1, i] = v / const[_CPU, i]
        out[2, i] = v
    return status


_sample = entry(_sample_at, f"{addresses(8)}, float64, boolean, int64")
# the sample kernel and its signature, for a kernel that does more with the sample in the
# same call (``AtiSensor.sample_through``)
SAMPLE_AT, SAMPLE_SIGNATURE = _sample_at, f"{addresses(8)}, float64, boolean, int64"


class AtiSensor(HoldsAddresses):
    """The sensor + Net F/T box: true wrench in, :class:`RdtRecord` out.

    ``seed`` drives two independent streams (noise, drift), so switching drift off
    does not change the noise a given seed produces.  Same config + seed + inputs
    give the same records.
    """

    def __init__(
        self,
        config: AtiConfig,
        seed: int,
        *,
        rdt_sequence_start: int = 1,
        ft_sequence_start: int = 1,
        clock_origin_ns: int | None = None,
    ) -> None:
        if not isinstance(config, AtiConfig):
            raise TypeError(f"config must be an AtiConfig, got {type(config).__name__}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        for name, v in (("rdt_sequence_start", rdt_sequence_start), ("ft_sequence_start", ft_sequence_start)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= v <= UINT32_MASK:
                raise ValueError(f"{name} must be a uint32, got {v!r}")
        self.config = config
        self.seed = int(seed)
        noise_ss, drift_ss = np.random.SeedSequence(self.seed).spawn(2)
        self._noise_rng = np.random.Generator(np.random.PCG64(noise_ss))
        self._drift_rng = np.random.Generator(np.random.PCG64(drift_ss))

        # Constants pulled out of the config once.
        self._bias = np.array(config.bias)
        self._noise_std = np.array(config.noise_std)
        self._drift_std = np.array(config.bias_drift_std)
        self._drift_on = bool(np.any(self._drift_std > 0))
        self._range = np.array(config.ranges)
        self._full_scale = np.array(config.full_scale)
        self._neg_full_scale = -self._full_scale
        self._cpu = np.array(config.counts_per_unit)
        self._step = np.array(config.step_counts)
        self._clip = config.saturation == "clip"
        self._period_ns = config.sample_period_ns

        # Scratch buffers: a sample allocates only the record's own counts (and the record).

        self._const = np.stack([self._bias, self._noise_std, self._range, self._full_scale, self._cpu, self._step,
                                self._drift_std, _SAT_BITS_ARRAY.astype(np.float64)])
        self._state = np.zeros((3, 6))  # drift, tare, the tare's running sum
        self._drift, self._tare, self._tare_acc = self._state  # views
        # [samples still to average, samples in the average], whole numbers in float64 for the kernel
        self._tare_state = np.zeros(2)
        # a sample's counts and wrench, and the last finite sample's counts (repeated by a
        # non-finite one), all whole numbers in float64 where counts
        self._out = np.zeros((3, 6))
        self._const_at, self._state_at = address(self._const), address(self._state)
        self._tare_at, self._out_at = address(self._tare_state), address(self._out)
        # normals drawn a block at a time (exactly the numbers 6 per sample would give)
        self._noise_block = np.empty((0, 6))
        self._noise_i = 0
        self._drift_block = np.empty((0, 6))
        self._drift_i = 0
        self._x = np.zeros(6)  # the true wrench of the sample, where the kernel reads it
        self._x_at, self._noise_at, self._drift_at = address(self._x), 0, 0

        self._next_rdt = int(rdt_sequence_start)
        self._ft_start = int(ft_sequence_start)
        # the time the internal sample count starts at (None: the first reading's): a cell's
        # start makes ft_sequence - ft_sequence_start count the cell's cycles
        self._t0_ns: int | None = None if clock_origin_ns is None else int(clock_origin_ns)
        self._last_t_ns = self._t0_ns or 0
        self._sample_index = 0

    # -- commands -----------------------------------------------------------------

    def tare(self, n_samples: int = 1) -> None:
        """Software bias: average the next ``n_samples`` finite readings and subtract it.

        See the module docstring for exactly what is averaged and when it applies.
        Calling again restarts the average (the current tare stays until it ends).
        """
        if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 1:
            raise ValueError(f"n_samples must be an integer >= 1, got {n_samples!r}")
        self._tare_state[:] = (int(n_samples), int(n_samples))
        self._tare_acc[:] = 0.0

    def clear_tare(self) -> None:
        """Drop the tare (and any pending one): readings include bias and drift again."""
        self._tare[:] = 0.0
        self._tare_state[0] = 0

    @property
    def tare_pending(self) -> bool:
        return bool(self._tare_state[0] > 0)

    @property
    def tare_offset(self) -> np.ndarray:
        """(6,) what is currently subtracted from raw readings (N, Nm)."""
        return self._tare.copy()

    @property
    def offset(self) -> np.ndarray:
        """(6,) the true current offset, bias + drift (ground truth, for diagnostics)."""
        return self._bias + self._drift

    # -- streaming ----------------------------------------------------------------

    def read(self, true_wrench: np.ndarray, t_ns: int) -> RdtRecord:
        """One RDT record for the true wrench at sim time ``t_ns`` (integer ns)."""
        return self.sample(true_wrench, t_ns)[0]

    def sample(self, true_wrench: np.ndarray, t_ns: int) -> tuple[RdtRecord, np.ndarray]:
        """``read``, with the record's wrench in N / Nm (``RdtRecord.wrench``'s values; may
        be a view of a buffer the next call overwrites: copy it to keep it)."""
        rdt, ft, args = self._begin(true_wrench, t_ns)
        status = self._sampled(_sample(*args))
        return self.record(rdt, ft, status)

    def sample_through(self, kernel, true_wrench: np.ndarray | None, t_ns: int, *extra) -> tuple[int, int, int]:
        """``sample``'s numbers made by ``kernel``, which takes ``_sample_at``'s arguments, the
        record's rdt and ft sequences and ``extra``, calls ``_sample_at`` first and returns
        -1 when it did (nothing sampled: a non-finite input), else what it makes of the
        sample (a message's bytes: services.nodes.ft_sensor).  Returns (rdt_sequence,
        ft_sequence, what the kernel returned); ``record`` makes the record after it.
        ``true_wrench`` None: the caller has written it in ``input``."""
        rdt, ft, args = self._begin(true_wrench, t_ns)
        return rdt, ft, self._sampled(kernel(*args, rdt, ft, *extra))

    def _sampled(self, result: int) -> int:
        """After a sample's kernel returned ``result``: its row of noise is used, unless it sampled
        nothing (-1: a non-finite input draws none).  Returns ``result``."""
        if result != -1:
            self._noise_i += 1
        return result

    def record(self, rdt: int, ft: int, status: int) -> tuple[RdtRecord, np.ndarray]:
        """The record of the sample just taken, whose ``_sample_at`` status was ``status``
        (-1: a non-finite input, the last counts repeated), and its wrench."""
        out = self._out
        if status < 0:
            return RdtRecord(rdt, ft, _STATUS_NONFINITE, out[2].astype(np.int32)), out[2] / self._cpu
        return RdtRecord.trusted(rdt, ft, int(status), out[0].astype(np.int32)), out[1]

    @property
    def input(self) -> np.ndarray:
        """(6,) where the kernel reads the sample's true wrench (``sample_through`` with None)."""
        return self._x

    def _begin(self, true_wrench: np.ndarray | None, t_ns: int) -> tuple[int, int, tuple]:
        """A sample's bookkeeping before its kernel: the true wrench where the kernel reads it,
        the clock advanced, the record's sequences, this sample's rows of drift and noise
        (drawn a block at a time).  Returns (rdt_sequence, ft_sequence, ``_sample_at``'s arguments)."""
        if true_wrench is not None:
            if np.shape(true_wrench) != (6,):
                raise ValueError(f"true_wrench must have shape (6,), got {np.shape(true_wrench)}")
            self._x[:] = true_wrench
        drift_scale = self._advance_time(int(t_ns))
        rdt = self._next_rdt
        self._next_rdt = (rdt + 1) & UINT32_MASK
        ft = (self._ft_start + self._sample_index) & UINT32_MASK
        di = 0
        if drift_scale > 0.0:
            di = self._drift_i
            if di >= len(self._drift_block):
                self._drift_block = self._drift_rng.standard_normal((_BLOCK, 6))
                self._drift_at = address(self._drift_block)
                di = 0
            self._drift_i = di + 1
        # the noise stream serves nothing else: a block drawn before a non-finite sample
        # holds the numbers the next finite one would have drawn
        ni = self._noise_i
        if ni >= len(self._noise_block):
            self._noise_block = self._noise_rng.standard_normal((_BLOCK, 6))
            self._noise_at = address(self._noise_block)
            ni = self._noise_i = 0
        return rdt, ft, (self._x_at, self._const_at, self._state_at, self._tare_at, self._noise_at, ni,
                         self._drift_at, di, drift_scale, self._clip, self._out_at)

    def _advance_time(self, t_ns: int) -> float:
        """Advance the sensor's clock to ``t_ns``; the drift step's sqrt(dt) (0: no drift step)."""
        if self._t0_ns is None:
            self._t0_ns = self._last_t_ns = t_ns
            return 0.0
        dt_ns = t_ns - self._last_t_ns
        # Time that goes backwards (a reset clock) neither undoes drift nor rewinds ft_sequence.
        if dt_ns <= 0:
            return 0.0
        self._last_t_ns = t_ns
        # The record carries the latest completed internal sample.
        index = (t_ns - self._t0_ns) // self._period_ns
        if index > self._sample_index:
            self._sample_index = index
        return math.sqrt(dt_ns * 1e-9) if self._drift_on else 0.0
