"""Seeded faults on the FRI link (``LinkFaults``: what happens to each packet) and their
specification as a scenario's ``cell.fri_*`` and the robot's ``--fri-*`` flags give it
(``LinkFaultSpec``: a value of plain fields, checked, that builds the faults)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from dataclasses import fields as dataclasses_fields

import numpy as np

from robot_sim.cycle import FRI_CYCLE_NS
from robot_sim.krc.packets import CommandPacket, is_integer

@dataclass
class LinkFaults:
    """Seeded faults on the path between KRC and remote.

    Command packets (remote -> KRC): lost with ``drop_probability``; otherwise
    damaged with ``corrupt_probability`` (one ``cart_pos`` element becomes NaN, on
    a copy) and delivered ``delay_ns`` plus a uniform 0..``jitter_ns`` later.
    A delivered command packet also arrives a second time with
    ``duplicate_probability`` (an exact copy, a uniform 0..``duplicate_spread_ns``
    after the first: the KRC must not apply it twice), and is held back
    ``reorder_lag_ns`` more with ``reorder_probability`` (1.5 ms by default: past
    its own deadline and after the next cycle's answer, so it arrives out of order).
    Measurement packets (KRC -> remote) are lost with
    ``measurement_drop_probability``: the remote never sees them and so cannot
    answer.  Each kind of packet draws from its own stream, a fixed number of
    draws per packet, so the same seed and the same calls give the same faults,
    and changing one probability does not reshuffle the others.  While ``active``
    is False (outside a scenario's fault window) the draws are made and ignored:
    packets pass untouched and the streams stay where a whole-run fault has them.
    """

    seed: int
    delay_ns: int = 0
    jitter_ns: int = 0
    drop_probability: float = 0.0
    corrupt_probability: float = 0.0
    measurement_drop_probability: float = 0.0
    duplicate_probability: float = 0.0
    duplicate_spread_ns: int = FRI_CYCLE_NS
    reorder_probability: float = 0.0
    reorder_lag_ns: int = 1_500_000
    active: bool = True
    dropped: int = field(default=0, init=False)
    corrupted: int = field(default=0, init=False)
    duplicated: int = field(default=0, init=False)
    reordered: int = field(default=0, init=False)
    measurements_dropped: int = field(default=0, init=False)
    _cmd_rng: np.random.Generator = field(init=False, repr=False, compare=False)
    _msr_rng: np.random.Generator = field(init=False, repr=False, compare=False)
    _order_rng: np.random.Generator = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        def need(ok: bool, name: str, what: str):
            if not ok:
                raise ValueError(f"LinkFaults.{name} = {getattr(self, name)!r}: {what}")

        need(is_integer(self.seed), "seed", "must be an integer (faults are always seeded)")
        need(is_integer(self.delay_ns) and self.delay_ns >= 0, "delay_ns", "must be an integer >= 0")
        need(is_integer(self.jitter_ns) and self.jitter_ns >= 0, "jitter_ns", "must be an integer >= 0")
        for name in ("duplicate_spread_ns", "reorder_lag_ns"):
            need(is_integer(getattr(self, name)) and getattr(self, name) >= 0, name, "must be an integer >= 0")
        for name in ("drop_probability", "corrupt_probability", "measurement_drop_probability",
                     "duplicate_probability", "reorder_probability"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and 0.0 <= v <= 1.0, name, "must be a probability in [0, 1]")
        # spawn keys are positional: the first two streams are what they were before the third existed
        cmd_seq, msr_seq, order_seq = np.random.SeedSequence(self.seed).spawn(3)
        self._cmd_rng = np.random.default_rng(cmd_seq)
        self._msr_rng = np.random.default_rng(msr_seq)
        self._order_rng = np.random.default_rng(order_seq)

    def measurement_lost(self) -> bool:
        """Whether the next measurement packet is lost on its way to the remote."""
        if self._msr_rng.random() < self.measurement_drop_probability and self.active:
            self.measurements_dropped += 1
            return True
        return False

    def transmit(self, packet: CommandPacket, t_sent_ns: int) -> list[tuple[CommandPacket, int]]:
        """Each arrival of ``packet`` as (packet as it arrives, arrival time), in order of
        arrival: none if it is lost, two if it is duplicated."""
        u_drop, u_corrupt, u_jitter, u_index = self._cmd_rng.random(4).tolist()
        u_dup, u_spread, u_reorder = self._order_rng.random(3).tolist() if self._orders else (1.0, 0.0, 1.0)
        if not self.active:
            return [(packet, int(t_sent_ns))]
        if u_drop < self.drop_probability:
            self.dropped += 1
            return []
        arrival = int(t_sent_ns) + self.delay_ns + (int(u_jitter * (self.jitter_ns + 1)) if self.jitter_ns else 0)
        if u_reorder < self.reorder_probability:
            self.reordered += 1
            arrival += self.reorder_lag_ns
        if u_corrupt < self.corrupt_probability:
            self.corrupted += 1
            try:
                damaged = np.array(packet.cart_pos, dtype=np.float64)
                damaged.reshape(-1)[int(u_index * damaged.size)] = np.nan
                packet = replace(packet, cart_pos=damaged)
            except Exception:
                pass  # already beyond repair: deliver it as it is, the KRC rejects it anyway
        if u_dup < self.duplicate_probability:
            self.duplicated += 1
            return [(packet, arrival), (packet, arrival + int(u_spread * (self.duplicate_spread_ns + 1)))]
        return [(packet, arrival)]

    @property
    def _orders(self) -> bool:
        # the third stream is drawn only where it is used: a run without these faults
        # costs nothing more per packet
        return self.duplicate_probability > 0.0 or self.reorder_probability > 0.0


class LinkFaultError(ValueError):
    """A fault specification that cannot be used: ``field`` (e.g. ``packet_loss``), what is
    expected (``problem``) and the ``value``."""

    def __init__(self, field_name: str, problem: str, value):
        super().__init__(f"{field_name}: {problem}, got {value!r}")
        self.field, self.problem, self.value = field_name, problem, value


_PROBABILITY, _MS, _SECONDS = "probability", "ms", "seconds"


def _fault(default: float, kind: str, doc: str):
    return field(default=default, metadata={"kind": kind, "doc": doc})


@dataclass(frozen=True)
class LinkFaultSpec:
    """The FRI link's faults as a study sets them, checked here once: a scenario's
    ``cell.fri_<field>`` and the robot's ``--fri-<field>`` flags are these fields.
    ``link_faults`` is the seeded model of them (``LinkFaults``), ``active`` the window."""

    packet_loss: float = _fault(0.0, _PROBABILITY, "probability that a command packet is lost on the FRI link")
    delay_ms: float = _fault(0.0, _MS, "every command packet arrives this much later, ms")
    jitter_ms: float = _fault(0.0, _MS, "and a further uniform 0..this, ms (reorders late answers)")
    corruption: float = _fault(0.0, _PROBABILITY, "probability that a command packet arrives damaged (the KRC "
                                                  "rejects it)")
    duplication: float = _fault(0.0, _PROBABILITY, "probability that a command packet arrives twice (the copy "
                                                   "0..1 cycle after it)")
    reordering: float = _fault(0.0, _PROBABILITY, "probability that a command packet is held back 1.5 ms (it "
                                                  "arrives after the next cycle's)")
    faults_from_s: float = _fault(0.0, _SECONDS, "the faults act from this many seconds into each episode")
    faults_until_s: float = _fault(math.inf, _SECONDS, "... until this many seconds into it (default: to its end)")

    MAX_DELAY_MS = 1000.0

    def __post_init__(self):
        for f in dataclasses_fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                    or math.isnan(value):
                raise LinkFaultError(f.name, "expected a number", value)
            kind = f.metadata["kind"]
            if kind == _PROBABILITY and not 0.0 <= value <= 1.0:
                raise LinkFaultError(f.name, "expected a probability in [0, 1]", value)
            if kind == _MS and not 0.0 <= value <= self.MAX_DELAY_MS:
                raise LinkFaultError(f.name, f"expected a number of ms in [0, {self.MAX_DELAY_MS:g}]", value)
            if f.name == "faults_from_s" and not 0.0 <= value < math.inf:
                raise LinkFaultError(f.name, "expected a finite number of seconds >= 0", value)
            object.__setattr__(self, f.name, float(value))
        if not self.faults_until_s > self.faults_from_s:
            raise LinkFaultError("faults_until_s", f"expected a number of seconds > the window's start "
                                                   f"({self.faults_from_s})", self.faults_until_s)

    def link_faults(self, seed: int) -> LinkFaults | None:
        """The seeded fault model, or None when the link is clean."""
        if not (self.packet_loss or self.corruption or self.duplication or self.reordering or self.delay_ms
                or self.jitter_ms):
            return None
        return LinkFaults(seed=seed, drop_probability=self.packet_loss, delay_ns=round(self.delay_ms * 1e6),
                          jitter_ns=round(self.jitter_ms * 1e6), corrupt_probability=self.corruption,
                          duplicate_probability=self.duplication, reorder_probability=self.reordering)

    def active(self, episode_s: float) -> bool:
        """Whether the faults act ``episode_s`` seconds into an episode."""
        return self.faults_from_s <= episode_s < self.faults_until_s
