"""The robot's KRC over UDP (``--wire udp``): the lab's FRI 1.0 at the edge of the robot
node.  Every cycle the measurement datagram goes to the remote, the command datagram
that answers it before the cycle ends is handed to the FRI link, and a KRL program
starts and stops command mode as the remote asks; with ``--krl testbench`` the run's own
commander is the remote and the KRL channels carry what a ``robot/command`` would (the
goal, the hold, the estimate it used), read here and handed to the node as such.  Both
datagrams of every cycle can also go out on ``fri/datagram``, bytes and decoded."""

from __future__ import annotations

import dataclasses

from robot_sim.krc.krl import (TB_EPISODE, TB_ESTIMATE_SEQ, TB_GOAL_REACHED, TB_GRAVITY_COMPENSATION, TB_HOLD,
                               TB_HOLDS, TB_KIND, TB_KINDS)
from robot_sim.krc.packets import ControlMode, FriQuality, FriState
from robot_sim.wire.fri_udp import host_port
from services.runtime.messages import FRI_DATAGRAM, datagram_fields
from services.transport.lab.krc_udp import UdpKrc


@dataclasses.dataclass(frozen=True)
class Taken:
    """A command datagram the KRC took for the open cycle, and what its KRL block said."""

    latency_ns: int
    arrived_ns: int
    goal_reached: bool
    hold: str
    estimate_seq: int


class RobotKrcOverUdp:
    """The robot node's FRI link over UDP, for its ``cell`` (what the node calls each cycle)."""

    def __init__(self, cell, config, clock):
        self.cell = cell
        self.krl_name = config.krl
        # --krl testbench: the run's own commander is the remote; it passes each measurement on
        # as robot/state (as the lab's FRI component did for its graph), so the robot does not
        self.relayed = config.krl == "testbench"
        self.wire_topic = bool(config.wire_topic)
        self.krc = UdpKrc(cell, host_port(config.fri_remote, "fri_remote"),
                          host_port(config.fri_bind, "fri_bind", listen=True), krl=config.krl, clock=clock.now_ns)
        self._datagrams: list = []  # (seq, stamp_ns, sent_ns, direction, bytes) of the open cycle
        self._krl_events = 0  # the KRL program's events before the episode
        self._wire0 = None  # the endpoint's counters when the episode began

    def begin_episode(self) -> None:
        # a cycle an earlier episode opened and never closed (it failed mid-cycle): its
        # measurement's copy is not this episode's to record
        self._datagrams.clear()
        self._krl_events = len(self.krc.krl.events)
        self._wire0 = dataclasses.replace(self.krc.endpoint.counters)

    def answered(self) -> bool:
        """The KRC waits for the remote's datagram until the cycle ends."""
        return self.krc.answered()

    def send(self, m, *, episode: int, kind: str, gravity_compensation: bool) -> None:
        if self.relayed:
            krl = self.krc.krl.krl_to
            krl.ints[TB_EPISODE - 1] = episode
            krl.ints[TB_KIND - 1] = TB_KINDS.index(kind) if episode >= 0 else 0
            krl.set_flag(TB_GRAVITY_COMPENSATION, gravity_compensation)
        if self.krc.send(m) and self.wire_topic:
            self._datagrams.append((m.seq, m.stamp_ns, self.krc.sent_ns, "measurement", self.krc.last_sent))

    def take(self, m) -> Taken | None:
        """The open cycle's command datagram, if it came, with what its KRL block says (what
        the testbench's remote says there; meaningless for a lab's remote)."""
        krc = self.krc
        if krc.take(m) is None:
            return None
        arrived = krc.sent_ns + krc.latency_ns
        if self.wire_topic:
            self._datagrams.append((m.seq, m.stamp_ns, arrived, "command", krc.last_accepted))
        frm = krc.endpoint.krl_accepted
        hold = int(frm.ints[TB_HOLD - 1])
        return Taken(krc.latency_ns, arrived, frm.flag(TB_GOAL_REACHED),
                     TB_HOLDS[hold] if 0 <= hold < len(TB_HOLDS) else "other", int(frm.ints[TB_ESTIMATE_SEQ - 1]))

    def publish_datagrams(self, bus) -> bool:
        """The cycle's datagrams on fri/datagram, once it has stepped: decoding one for the
        recording costs as much as the cycle's physics (~70 us), and made where it crossed
        the wire it kept the remote's answer waiting, then the step.  False: there were none."""
        if not self._datagrams:
            return False
        for seq, stamp_ns, sent_ns, direction, data in self._datagrams:
            bus.publish(FRI_DATAGRAM.topic, *FRI_DATAGRAM.pack(
                seq=seq, stamp_ns=stamp_ns, sent_ns=sent_ns, direction=direction,
                **datagram_fields(data, direction)))
        self._datagrams.clear()
        return True

    def summary(self, ep) -> dict:
        """The episode's wire: the datagrams' counters, the KRL program's events, the link's
        state changes (``ep``: the robot's EpisodeJudge)."""
        krc, krl, cycle_ns = self.krc, self.krc.krl, self.cell.cycle_ns
        counters = {k: v - getattr(self._wire0, k) for k, v in dataclasses.asdict(krc.endpoint.counters).items()}
        return {"address": f"{krc.address[0]}:{krc.address[1]}", "remote": f"{krc.remote[0]}:{krc.remote[1]}",
                "krl": self.krl_name, "datagrams": counters, "last_reject_reason": krc.endpoint.last_reject_reason,
                "krl_events": [dict(seq=e.seq, at_s=(e.seq - ep.first_seq + 1) * cycle_ns / 1e9, kind=e.kind, text=e.text)
                               for e in krl.events[self._krl_events:]],
                "refusal": krl.refusal, "first_command_refusals": list(ep.refusals),
                "safety_stop": ep.safety_stop,
                "command_mode_s": ep.cmd_cycles * cycle_ns / 1e9,
                "states": [dict(seq=q, at_s=(q - ep.first_seq + 1) * cycle_ns / 1e9,
                                state=FriState(st).name, quality=FriQuality(qu).name) for q, st, qu in ep.states],
                "control_mode": ControlMode(self.cell.fri.control_mode).name}

    def status(self) -> dict:
        return {"address": list(self.krc.address), "remote": list(self.krc.remote), "krl": self.krl_name}

    def close(self) -> None:
        self.krc.close()
