"""The ft_sensor node: the ATI F/T sensor (``robot_sim.ati``), once per robot cycle.

Samples the tool wrench the robot publishes on ``robot/contact`` with the ATI
model (bias, drift, noise, quantisation, saturation) and publishes an RDT-like
record on ``ft/wrench`` carrying the same cycle ``seq``.  Realtime: the newest
contact message, skipping a backlog (``latest``).  Control: ``tare`` (software
bias over the next N samples).  A malformed contact message is dropped and
counted by the transport; a non-finite wrench sets the sensor's error bit
(robot_sim.ati) instead of reaching the wire.
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


@dataclass(frozen=True)
class FtSensorConfig:
    seed: int = option(0, "seed of the sensor's noise and drift")
    noise_scale: float = option(1.0, "white noise as a multiple of the Mini45's (0: none)")

    def __post_init__(self):
        if not (math.isfinite(self.noise_scale) and self.noise_scale >= 0):
            raise ValueError(f"noise_scale must be a finite number >= 0, got {self.noise_scale!r}")

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
        self.publications = [Publication("ft/wrench")]
        self.subscriptions = [Subscription("robot/contact", self.on_contact, latest=True)]

    def on_contact(self, msg, recv_ns, raw) -> None:
        with self._lock:
            self._wrench[:] = msg["wrench"]
            rec = self.ati.read(self._wrench, msg["stamp_ns"])
            w = rec.wrench(self.ati_config)
        self.bus.publish("ft/wrench", *FT_WRENCH.pack(
            seq=msg["seq"], stamp_ns=msg["stamp_ns"], sent_ns=self.clock.now_ns(),
            rdt_sequence=int(rec.rdt_sequence), ft_sequence=int(rec.ft_sequence), status=int(rec.status),
            counts=rec.counts.tolist(), counts_per_force=self._cpf, counts_per_torque=self._cpt,
            wrench=w))

    def handlers(self):
        return {"tare": self.tare}

    def tare(self, p: dict) -> None:
        with self._lock:
            self.ati.tare(int(p.get("samples", 100)))
