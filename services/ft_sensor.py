"""ft_sensor: the ATI F/T sensor, 1 kHz.

Samples the tool wrench the robot publishes on ``robot/contact`` with the ATI
model (bias, drift, noise, quantisation, saturation) and publishes an RDT-like
record on ``ft/wrench`` carrying the same cycle ``seq``.  On the realtime
clock a sensor that has fallen behind samples the newest contact message and
skips the older ones (``Service.subscribe(latest=True)``: counted as lost);
in lockstep it answers every one.  Control: ``tare``
(software bias over the next N samples), ``status``, ``shutdown``.  A
malformed contact message is dropped and counted; a non-finite wrench sets the
sensor's error bit (robot_sim.ati) instead of reaching the wire.
"""

from __future__ import annotations

import argparse
import sys
import threading
from dataclasses import dataclass

import numpy as np

from robot_sim.ati import AtiConfig, AtiSensor
from services.runtime.messages import FT_WRENCH
from services.runtime.service import Service, now_ns
from services.runtime.session import ZenohOptions, add_zenoh_arguments, zenoh_options


@dataclass(frozen=True)
class FtSensorConfig:
    run_id: str
    zenoh: ZenohOptions
    sched_fifo: int = 0  # SCHED_FIFO priority, 0: none
    cpus: tuple = ()  # CPU affinity of the whole process, (): any
    seed: int = 0
    clock: str = "lockstep"


class FtSensorProcess:
    def __init__(self, config: FtSensorConfig, svc: Service):
        self.svc = svc
        self.ati_config = AtiConfig.mini45()
        self.ati = AtiSensor(self.ati_config, config.seed)
        self._lock = threading.Lock()
        self._pub = svc.publisher("ft/wrench")
        self._wrench = np.zeros(6)
        svc.subscribe("robot/contact", self.on_contact, latest=config.clock == "realtime")

    def on_contact(self, msg, recv_ns, raw) -> None:
        with self._lock:
            self._wrench[:] = msg["wrench"]
            rec = self.ati.read(self._wrench, msg["stamp_ns"])
            w = rec.wrench(self.ati_config)
        self._pub.put(FT_WRENCH.encode(
            seq=msg["seq"], stamp_ns=msg["stamp_ns"], sent_ns=now_ns(), rdt_sequence=int(rec.rdt_sequence),
            ft_sequence=int(rec.ft_sequence), status=int(rec.status), counts=[int(c) for c in rec.counts],
            counts_per_force=float(self.ati_config.counts_per_force),
            counts_per_torque=float(self.ati_config.counts_per_torque), wrench=w))

    def tare(self, p: dict) -> None:
        with self._lock:
            self.ati.tare(int(p.get("samples", 100)))

    def serve(self) -> None:
        self.svc.serve({"tare": self.tare})


def main(config: FtSensorConfig) -> int:
    with Service("ft_sensor", config.run_id, config.zenoh, sched_fifo=config.sched_fifo,
                 cpus=config.cpus) as svc:
        proc = FtSensorProcess(config, svc)
        svc.log("ready")
        proc.serve()
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="etar-ft-sensor", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-id", required=True)
    parser.add_argument("--clock", choices=("lockstep", "realtime"), default="lockstep",
                        help="realtime: sample the newest contact message, skipping any backlog; "
                             "lockstep: every one")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sensor's noise and drift")
    add_zenoh_arguments(parser)
    return parser


def cli(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return main(FtSensorConfig(run_id=args.run_id, zenoh=zenoh_options(args), seed=args.seed,
                               sched_fifo=args.sched_fifo, cpus=args.cpus, clock=args.clock))


if __name__ == "__main__":
    sys.exit(cli())
