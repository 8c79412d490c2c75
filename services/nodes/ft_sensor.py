"""The ft_sensor node: the ATI F/T sensor (``robot_sim.ati.sensor``), once per robot cycle.

Samples the tool wrench the robot publishes on ``robot/contact`` with the ATI
model (bias, drift, noise, quantisation, saturation) and publishes an RDT-like
record on ``ft/wrench`` carrying the same cycle ``seq``.  Realtime: the newest
contact message, skipping a backlog (``latest``).  Control: ``tare`` (software
bias over the next N samples).  A malformed contact message is dropped and
counted by the transport; a non-finite wrench sets the sensor's error bit
(robot_sim.ati.sensor) instead of reaching the wire.

Fault injection (``--fault``, from ``--fault-after`` s of simulated time into
each episode, for the rest of it): ``stop``, the RDT stream stops (nothing more
is published); ``saturate``, the load on the gauges is far beyond the Mini45's
range (the ATI model clips and sets its saturation bits); ``nan``, the gauges
read NaN (the model repeats the last counts and sets its non-finite-input status
bit).  The last two go through the sensor model itself, so the status bits are
the ones a real record would carry.

``--netft HOST`` serves the sensor as an ATI Net F/T box on that address
(``robot_sim.wire.netft``): RDT over UDP (49152), the HTTP pages (80) and the calibration
channel (TCP 49151), ports configurable; every record the ATI model makes goes to the
box's streaming clients, and a client's bias request tares the model (so the box and
``ft/wrench`` read the same).  Every RDT datagram sent goes out on ``netft/rdt`` too, as
bytes and decoded.
"""

from __future__ import annotations

import base64
import dataclasses
import ipaddress
import math
import threading
from dataclasses import dataclass

import numpy as np
from numba import njit

from kernel_plumbing.addresses import JIT, addresses, carray_at, entry, int64_array_at
from robot_sim.ati.sensor import SAMPLE_AT, SAMPLE_SIGNATURE, AtiConfig, AtiSensor
from robot_sim.wire.netft import CALIBRATION_PORT, HTTP_PORT, RDT_PORT, RDT_RECORD
from services.runtime.bus import Node, Publication, Subscription
from services.runtime.config import check_seed, option
from services.runtime.message_bytes import WRITE_AT, MessageBytes
from services.runtime.messages import FT_WRENCH, NETFT_RDT, ROBOT_CONTACT

SENSOR_FAULTS = ("none", "stop", "saturate", "nan")
# what a saturating load is: ten times the Mini45's largest range on every axis
SATURATING_LOAD = 10.0


def rdt_fields(data: bytes) -> dict:
    """NETFT_RDT's ``bytes`` and ``records`` for an RDT datagram the box sent."""
    records = [dict(zip(("rdt_sequence", "ft_sequence", "status"), r[:3]), counts=list(r[3:]))
               for r in RDT_RECORD.iter_unpack(data[:len(data) - len(data) % RDT_RECORD.size])]
    return {"bytes": base64.b64encode(data).decode("ascii"), "records": records}


# ft/wrench's integers in its MessageBytes, in the message's order (checked where it is made)
_RECORD_INTS = ("seq", "stamp_ns", "sent_ns", "rdt_sequence", "ft_sequence", "status")
_STATUS = _RECORD_INTS.index("status")


@njit(**JIT)
def _record_at(x_at, const_at, state_at, tare_at, noise_at, ni, drift_at, di, drift_scale, clip, out_at,
               rdt, ft, seq, stamp_ns, sent_ns, counts_at, wrench_at,
               fn, layout_at, n_fields, keys_at, n_keys, ints_at, n_ints, floats_at, n_floats, bytes_at, n_bytes):
    """One ATI sample and its ``ft/wrench`` bytes in one call (``AtiSensor.sample_through``):
    the sensor's kernel, then the record's numbers where the message's MessageBytes keeps
    them (its counts and wrench at ``counts_at`` and ``wrench_at`` of its floats) and the
    message written.  -1: a non-finite input (nothing sampled); -2: sampled, but the
    message could not be written (its status in the ints); else the message's length."""
    status = SAMPLE_AT(x_at, const_at, state_at, tare_at, noise_at, ni, drift_at, di, drift_scale, clip, out_at)
    if status < 0:
        return -1
    ints = int64_array_at(ints_at, n_ints)
    ints[0], ints[1], ints[2], ints[3], ints[4], ints[5] = seq, stamp_ns, sent_ns, rdt, ft, status
    floats, out = carray_at(floats_at, (n_floats,)), carray_at(out_at, (3, 6))
    for i in range(6):
        floats[counts_at + i] = out[0, i]
        floats[wrench_at + i] = out[1, i]
    n = WRITE_AT(fn, layout_at, n_fields, keys_at, n_keys, ints_at, n_ints, floats_at, n_floats, bytes_at, n_bytes)
    return n if n >= 0 else -2


_RECORD = entry(_record_at, f"{SAMPLE_SIGNATURE}, {addresses(18)}") if MessageBytes.available else None


@dataclass(frozen=True)
class FtSensorConfig:
    seed: int = option(0, "seed of the sensor's noise and drift, >= 0")
    noise_scale: float = option(1.0, "white noise as a multiple of the Mini45's (0: none)", metavar="FACTOR")
    fault: str = option("none", "fault injection: the sensor fails from --fault-after s into each episode "
                                "(stop: no more records; saturate: beyond its range; nan: the gauges read NaN)",
                        choices=SENSOR_FAULTS)
    fault_after: float = option(0.0, "fault injection: when --fault starts, seconds of simulated time into each "
                                     "episode", metavar="S")
    netft: str = option("", "serve the sensor as a Net F/T box on this IPv4 address (e.g. 127.0.0.1; empty: no "
                            "box): RDT on UDP, netftapi2.xml over HTTP, calibration on TCP", metavar="HOST")
    netft_topic: bool = option(True, "--netft: publish every RDT datagram the box sends on netft/rdt, bytes and "
                                     "decoded (the recording of the wire)")
    netft_rdt_port: int = option(RDT_PORT, "--netft: the RDT UDP port (0: any free one)", metavar="PORT")
    netft_http_port: int = option(HTTP_PORT, "--netft: the HTTP port (0: any free one)", metavar="PORT")
    netft_calibration_port: int = option(CALIBRATION_PORT, "--netft: the TCP calibration port (0: any free one)",
                                         metavar="PORT")

    def __post_init__(self):
        check_seed(self.seed)
        if not (math.isfinite(self.noise_scale) and self.noise_scale >= 0):
            raise ValueError(f"noise_scale must be a finite number >= 0, got {self.noise_scale!r}")
        if self.fault not in SENSOR_FAULTS:
            raise ValueError(f"fault must be one of {', '.join(SENSOR_FAULTS)}, got {self.fault!r}")
        if not (math.isfinite(self.fault_after) and self.fault_after >= 0):
            raise ValueError(f"fault_after must be a finite number of seconds >= 0, got {self.fault_after!r}")
        if self.netft:
            try:
                ipaddress.IPv4Address(self.netft)
            except ValueError:
                raise ValueError(f"netft must be an IPv4 address, got {self.netft!r}") from None
        for name in ("netft_rdt_port", "netft_http_port", "netft_calibration_port"):
            port = getattr(self, name)
            if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
                raise ValueError(f"{name} must be a port number 0..65535, got {port!r}")

    def ati(self) -> AtiConfig:
        base = AtiConfig.mini45()
        if self.noise_scale == 1.0:
            return base
        return dataclasses.replace(base, noise_std=base.noise_std * self.noise_scale)


class FtSensorNode(Node):
    name = "ft_sensor"

    def __init__(self, config: FtSensorConfig, bus, clock, *, run_id: str = "", mode: str = "lockstep",
                 netft_box=None, **_):
        super().__init__(bus, clock)
        self.ati_config = config.ati()
        # the sensor's samples counted from the cell's start: a record's ft_sequence is then the
        # robot cycle's seq (both 1 at t = 0), which is how a Net F/T client lines them up
        self.ati = AtiSensor(self.ati_config, config.seed, clock_origin_ns=0)
        self._cpf = float(self.ati_config.counts_per_force)
        self._cpt = float(self.ati_config.counts_per_torque)
        self._lock = threading.Lock()
        self._wrench = self.ati.input  # a record's true wrench, written where the sensor's kernel reads it
        self.fault = config.fault
        self.fault_after_ns = int(config.fault_after * 1e9)
        self._episode, self._episode_t0 = None, 0
        self.faulted = 0  # records the injected fault changed (or, stopped, never sent)
        self.publications = [Publication(FT_WRENCH.topic)]
        # over Zenoh only the bytes cross: the dict beside them would be made for nobody
        self._dicts = getattr(bus, "carries_dicts", True)
        self._bytes = MessageBytes(FT_WRENCH, whole=("counts",)) if MessageBytes.available else None
        if self._bytes is not None:
            slots, floats = self._bytes.slots, self._bytes.floats
            floats[slots["counts_per_force"][1]], floats[slots["counts_per_torque"][1]] = self._cpf, self._cpt
            # where a sample's counts and wrench go, every cycle
            self._counts_at, self._wrench_at = slots["counts"][1], slots["wrench"][1]
            if [slots[name] for name in _RECORD_INTS] != [("ints", i, 1) for i in range(len(_RECORD_INTS))]:
                raise RuntimeError(f"ft/wrench's integers are no longer {_RECORD_INTS} in this order: _record_at "
                                   f"writes them so")
            self._record_args = (self._counts_at, self._wrench_at, *self._bytes.kernel_args)
        self.box = None
        if config.netft:
            if config.netft_topic:
                self.publications.append(Publication(NETFT_RDT.topic, drop_when_congested=True))
            if netft_box is None:
                raise ValueError("netft: the service process brings the Net F/T box (services.transport.lab)")
            self.box = netft_box(self.ati_config, self._netft_bias, self._netft_sent if config.netft_topic else None)
        self._stamp = (0, 0)  # the cycle of the record the box is sending (seq, stamp_ns)
        # keep_tenth: realtime takes the newest contact but never skips a tenth cycle's,
        # whose wrench the estimator needs (it lost half of them on a crowded CPU)
        self.subscriptions = [Subscription(ROBOT_CONTACT.topic, self.on_contact, latest=True, keep_tenth=True)]

    def _injected(self, msg) -> bool:
        """Whether the injected fault acts on this record (episodes of the run only)."""
        if self.fault == "none" or msg["episode"] < 0:
            return False
        if msg["episode"] != self._episode:
            self._episode, self._episode_t0 = msg["episode"], msg["stamp_ns"]
        return msg["stamp_ns"] - self._episode_t0 >= self.fault_after_ns

    def on_contact(self, msg, recv_ns, raw) -> None:
        packed = self.sample(msg, message=self._dicts)
        if packed is not None:
            self.bus.publish(FT_WRENCH.topic, *packed)

    def sample(self, msg, message: bool = True) -> tuple | None:
        """The ATI record of one ``robot/contact``: ``ft/wrench`` as ``pack`` gives it, or None
        when the injected fault stopped the stream.  ``message=False``: nobody in this
        process reads the dict: the same bytes written by a kernel, and only the message's
        (seq, sent_ns) beside them (what a recorder needs)."""
        with self._lock:
            self._wrench[:] = msg["wrench"]
            if self._injected(msg):
                self.faulted += 1
                if self.fault == "stop":
                    return None
                if self.fault == "saturate":
                    self._wrench[:] = SATURATING_LOAD * float(np.max(self.ati_config.ranges))
                else:
                    self._wrench[:] = np.nan
            # the record's bytes too: Zenoh may hand over two contacts at once (a foreign peer's
            # copy beside the real one), and both would write the one byte buffer
            if not message and self.box is None and self._bytes is not None:  # _RECORD is built with it
                # nobody here needs the record itself: the sample and its bytes in one kernel call
                seq, stamp, sent = msg["seq"], msg["stamp_ns"], self.clock.now_ns()
                rdt, ft, n = self.ati.sample_through(_RECORD, None, stamp, seq, stamp, sent,
                                                     *self._record_args)
                if n >= 0:
                    return self._bytes.written(n), (seq, sent)
                rec, w = self.ati.record(rdt, ft, -1 if n == -1 else int(self._bytes.ints[_STATUS]))
            else:
                rec, w = self.ati.sample(self._wrench, msg["stamp_ns"])
            packed = self._packed(msg, rec, w, message)
        if self.box is not None:
            # outside the lock: a client's bias request (the box's thread) takes it
            self._stamp = (msg["seq"], msg["stamp_ns"])
            self.box.publish(rec)
        return packed

    def _packed(self, msg, rec, w, message: bool) -> tuple:
        if not message and self._bytes is not None:
            seq, sent, mb = msg["seq"], self.clock.now_ns(), self._bytes
            # its integers: the header, the sequences, the status (the counts are whole floats)
            mb.ints[:] = (seq, msg["stamp_ns"], sent, rec.rdt_sequence, rec.ft_sequence, rec.status)
            c, wr = self._counts_at, self._wrench_at
            mb.floats[c:c + 6] = rec.counts
            mb.floats[wr:wr + 6] = w
            payload = mb.write()
            if payload is not None:
                return payload, (seq, sent)
        return FT_WRENCH.pack(
            seq=msg["seq"], stamp_ns=msg["stamp_ns"], sent_ns=self.clock.now_ns(),
            rdt_sequence=int(rec.rdt_sequence), ft_sequence=int(rec.ft_sequence), status=int(rec.status),
            counts=rec.counts.tolist(), counts_per_force=self._cpf, counts_per_torque=self._cpt,
            wrench=w.tolist())

    def handlers(self):
        return {"tare": self.tare}

    def status(self) -> dict:
        status = {"fault": self.fault, "faulted": self.faulted}
        if self.box is not None:
            status["netft"] = dict(dataclasses.asdict(self.box.stats()), address=self.box.address,
                                   rdt_port=self.box.rdt_port, http_port=self.box.http_port,
                                   calibration_port=self.box.calibration_port)
        return status

    def close(self) -> None:
        if self.box is not None:
            self.box.close()

    def _netft_bias(self) -> None:
        """A client asked the box for a software bias: the sensor model is tared on its next
        sample, so what the box sends and ft/wrench agree."""
        with self._lock:
            self.ati.tare(1)

    def _netft_sent(self, peer, data: bytes) -> None:
        seq, stamp = self._stamp
        self.bus.publish(NETFT_RDT.topic, *NETFT_RDT.pack(seq=seq, stamp_ns=stamp, sent_ns=self.clock.now_ns(),
                                                      client=f"{peer[0]}:{peer[1]}", **rdt_fields(data)))

    def tare(self, p: dict) -> None:
        with self._lock:
            self.ati.tare(int(p.get("samples", 100)))
