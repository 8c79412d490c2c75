"""What an ATI Net F/T puts on the wire for one sample: the RDT record and its status word.

Apart from the sensor model (``robot_sim.ati.sensor``), which makes the records, so that a reader
of the wire (``services.transport.lab.netft_client``, ``robot_sim.wire.netft``'s wire layouts) loads
neither the model's compiled kernels nor numba: the estimator's process imports this, not
the model.  The record's layout and what each status bit means are in ``robot_sim.ati.sensor``'s
module docstring, beside the model that sets them.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np


class Calibration(Protocol):
    """What turns counts into N and Nm (an ``AtiConfig`` is one): the wire needs the value,
    not the sensor model."""

    counts_per_unit: np.ndarray  # (6,) counts per N (forces) and per Nm (torques)

INT32_MAX = 2**31 - 1
UINT32_MASK = 0xFFFFFFFF


class AtiStatus(enum.IntFlag):
    """Bits of :attr:`RdtRecord.status` (what each means: ``robot_sim.ati.sensor``'s module docstring)."""

    SAT_FX = 1 << 8
    SAT_FY = 1 << 9
    SAT_FZ = 1 << 10
    SAT_TX = 1 << 11
    SAT_TY = 1 << 12
    SAT_TZ = 1 << 13
    INPUT_NONFINITE = 1 << 14
    FT_OUT_OF_RANGE = 1 << 30
    ERROR = 1 << 31


SATURATION_BITS: tuple[AtiStatus, ...] = (
    AtiStatus.SAT_FX,
    AtiStatus.SAT_FY,
    AtiStatus.SAT_FZ,
    AtiStatus.SAT_TX,
    AtiStatus.SAT_TY,
    AtiStatus.SAT_TZ,
)


@dataclass(eq=False)
class RdtRecord:
    """One RDT record as the Net F/T sends it: sequences, status word, int32 counts."""

    rdt_sequence: int
    ft_sequence: int
    status: int
    counts: np.ndarray
    """(6,) int32: Fx, Fy, Fz, Tx, Ty, Tz in counts."""

    SIZE: ClassVar[int] = 36
    _WIRE: ClassVar[struct.Struct] = struct.Struct(">3I6i")

    def __post_init__(self) -> None:
        for name in ("rdt_sequence", "ft_sequence", "status"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= v <= UINT32_MASK:
                raise ValueError(f"RdtRecord.{name} must be a uint32, got {v!r}")
        counts = np.asarray(self.counts)
        if counts.shape != (6,) or counts.dtype.kind not in "iu":
            raise ValueError(f"RdtRecord.counts must be 6 integers, got {self.counts!r}")
        if counts.dtype != np.int32:
            if np.any(np.abs(counts.astype(np.int64)) > INT32_MAX):
                raise ValueError(f"RdtRecord.counts must fit int32, got {self.counts!r}")
            counts = counts.astype(np.int32)
        self.counts = counts

    @classmethod
    def trusted(cls, rdt_sequence: int, ft_sequence: int, status: int, counts: np.ndarray) -> "RdtRecord":
        """A record from values the sensor model itself made (uint32 sequences, int32
        counts): the checks of the constructor, which cost more than the sample, skipped."""
        rec = cls.__new__(cls)
        rec.rdt_sequence, rec.ft_sequence, rec.status, rec.counts = rdt_sequence, ft_sequence, status, counts
        return rec

    def wrench(self, config: Calibration) -> np.ndarray:
        """(6,) float64 wrench in N / Nm: counts / counts-per-unit."""
        return self.counts / config.counts_per_unit

    @property
    def ok(self) -> bool:
        return self.status == 0

    def flags(self) -> AtiStatus:
        """The status word as :class:`AtiStatus` (unknown bits are kept)."""
        return AtiStatus(self.status)

    def pack(self) -> bytes:
        """The 36-byte big-endian wire form of the real RDT record."""
        return self._WIRE.pack(self.rdt_sequence, self.ft_sequence, self.status, *self.counts.tolist())

    @classmethod
    def unpack(cls, data: bytes) -> RdtRecord:
        if len(data) != cls.SIZE:
            raise ValueError(f"an RDT record is {cls.SIZE} bytes, got {len(data)}")
        rdt, ft, status, *counts = cls._WIRE.unpack(data)
        return cls(rdt, ft, status, np.array(counts, dtype=np.int32))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RdtRecord):
            return NotImplemented
        return (
            self.rdt_sequence == other.rdt_sequence
            and self.ft_sequence == other.ft_sequence
            and self.status == other.status
            and np.array_equal(self.counts, other.counts)
        )

    __hash__ = None  # type: ignore[assignment]  # mutable
