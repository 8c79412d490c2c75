"""The ft_sensor node: the ATI F/T sensor (``robot_sim.ati``), once per robot cycle.

Samples the tool wrench the robot publishes on ``robot/contact`` with the ATI
model (bias, drift, noise, quantisation, saturation) and publishes an RDT-like
record on ``ft/wrench`` carrying the same cycle ``seq``.  Realtime: the newest
contact message, skipping a backlog (``latest``).  Control: ``tare`` (software
bias over the next N samples).  A malformed contact message is dropped and
counted by the transport; a non-finite wrench sets the sensor's error bit
(robot_sim.ati) instead of reaching the wire.

Fault injection (``--fault``, from ``--fault-after`` s of simulated time into
each episode, for the rest of it): ``stop``, the RDT stream stops (nothing more
is published); ``saturate``, the load on the gauges is far beyond the Mini45's
range (the ATI model clips and sets its saturation bits); ``nan``, the gauges
read NaN (the model repeats the last counts and sets its non-finite-input status
bit).  The last two go through the sensor model itself, so the status bits are
the ones a real record would carry.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass

import numpy as np

from robot_sim.ati import AtiConfig, AtiSensor
from services.runtime.bus import Node, Publication, Subscription
from services.runtime.config import option
from services.runtime.messages import FT_WRENCH

SENSOR_FAULTS = ("none", "stop", "saturate", "nan")
# what a saturating load is: ten times the Mini45's largest range on every axis
SATURATING_LOAD = 10.0


@dataclass(frozen=True)
class FtSensorConfig:
    seed: int = option(0, "seed of the sensor's noise and drift")
    noise_scale: float = option(1.0, "white noise as a multiple of the Mini45's (0: none)", metavar="FACTOR")
    fault: str = option("none", "fault injection: the sensor fails from --fault-after s into each episode "
                                "(stop: no more records; saturate: beyond its range; nan: the gauges read NaN)",
                        choices=SENSOR_FAULTS)
    fault_after: float = option(0.0, "fault injection: when --fault starts, seconds of simulated time into each "
                                     "episode", metavar="S")

    def __post_init__(self):
        if not (math.isfinite(self.noise_scale) and self.noise_scale >= 0):
            raise ValueError(f"noise_scale must be a finite number >= 0, got {self.noise_scale!r}")
        if self.fault not in SENSOR_FAULTS:
            raise ValueError(f"fault must be one of {', '.join(SENSOR_FAULTS)}, got {self.fault!r}")
        if not (math.isfinite(self.fault_after) and self.fault_after >= 0):
            raise ValueError(f"fault_after must be a finite number of seconds >= 0, got {self.fault_after!r}")

    def ati(self) -> AtiConfig:
        base = AtiConfig.mini45()
        if self.noise_scale == 1.0:
            return base
        return dataclasses.replace(base, noise_std=base.noise_std * self.noise_scale)


class FtSensorNode(Node):
    name = "ft_sensor"

    def __init__(self, config: FtSensorConfig, bus, clock, *, run_id: str = "", mode: str = "lockstep", **_):
        super().__init__(bus, clock)
        self.ati_config = config.ati()
        self.ati = AtiSensor(self.ati_config, config.seed)
        self._cpf = float(self.ati_config.counts_per_force)
        self._cpt = float(self.ati_config.counts_per_torque)
        self._lock = threading.Lock()
        self._wrench = np.zeros(6)
        self.fault = config.fault
        self.fault_after_ns = int(config.fault_after * 1e9)
        self._episode, self._episode_t0 = None, 0
        self.faulted = 0  # records the injected fault changed (or, stopped, never sent)
        self.publications = [Publication("ft/wrench")]
        # keep_tenth: realtime takes the newest contact but never skips a tenth cycle's,
        # whose wrench the estimator needs (it lost half of them on a crowded CPU)
        self.subscriptions = [Subscription("robot/contact", self.on_contact, latest=True, keep_tenth=True)]

    def _injected(self, msg) -> bool:
        """Whether the injected fault acts on this record (episodes of the run only)."""
        if self.fault == "none" or msg["episode"] < 0:
            return False
        if msg["episode"] != self._episode:
            self._episode, self._episode_t0 = msg["episode"], msg["stamp_ns"]
        return msg["stamp_ns"] - self._episode_t0 >= self.fault_after_ns

    def on_contact(self, msg, recv_ns, raw) -> None:
        with self._lock:
            self._wrench[:] = msg["wrench"]
            if self._injected(msg):
                self.faulted += 1
                if self.fault == "stop":
                    return
                if self.fault == "saturate":
                    self._wrench[:] = SATURATING_LOAD * float(np.max(self.ati_config.ranges))
                else:
                    self._wrench[:] = np.nan
            rec = self.ati.read(self._wrench, msg["stamp_ns"])
            w = rec.wrench(self.ati_config)
        self.bus.publish("ft/wrench", *FT_WRENCH.pack(
            seq=msg["seq"], stamp_ns=msg["stamp_ns"], sent_ns=self.clock.now_ns(),
            rdt_sequence=int(rec.rdt_sequence), ft_sequence=int(rec.ft_sequence), status=int(rec.status),
            counts=rec.counts.tolist(), counts_per_force=self._cpf, counts_per_torque=self._cpt,
            wrench=w))

    def handlers(self):
        return {"tare": self.tare}

    def status(self) -> dict:
        return {"fault": self.fault, "faulted": self.faulted}

    def tare(self, p: dict) -> None:
        with self._lock:
            self.ati.tare(int(p.get("samples", 100)))
