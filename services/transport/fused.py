"""Every node of a run in one process, its FRI cycles stepped without a bus: the fused engine.

The per-message engine (``services.transport.inproc``) queues every message a node
publishes and hands it to each subscriber's handler in turn.  This one knows the 1 kHz
path and walks it once per cycle: the robot measures (``robot/state``, ``robot/contact``),
the commander answers the measurement, the sensor samples the contact, the teacher's
hand answers both, the estimator takes its instant's state and wrench and the
commander the estimate; every message is packed once, handed to the recorder and to
any other subscriber (the live view's bridge), and the robot closes the cycle with its
answers directly.  Each node does its own work in the same methods its handlers call
(``take_state``, ``sample``, ``take_phase``, ...), so the two engines cannot drift; the
order is the queue's (a node's inputs in the order the queue delivers them), and the
same seed records the same messages either way (tests/e2e/test_engines.py).

What is the same as the per-message engine: the cycle engine (``services.runtime.cycle``)
and its lockstep rules (a cycle still waiting once everything is delivered: the nodes
are told, then it closes with a missed answer), the control requests and every message
off the 1 kHz path (through the in-process bus), a node whose work raises counted as a
bad message of that node and topic while the run goes on.
"""

from __future__ import annotations

from services.runtime.messages import (ESTIMATOR_PHASE, FT_WRENCH, ROBOT_CONTACT,
                                       ROBOT_STATE, TEACHER_WRENCH, estimator_instant)
from services.transport.inproc import InProcessCell

# the roles whose 1 kHz work the fused cycle does itself; any other node gets the
# cycle's messages through its subscriptions
STEPPED = ("robot", "ft_sensor", "teacher", "phase_estimator", "impedance_commander", "recorder")
_STATE, _CONTACT, _WRENCH = ROBOT_STATE.topic, ROBOT_CONTACT.topic, FT_WRENCH.topic
_HAND, _PHASE = TEACHER_WRENCH.topic, ESTIMATOR_PHASE.topic


class FusedCell(InProcessCell):
    """The nodes of one run in this process, their episodes' cycles stepped by ``FusedCycle``
    (what the cycle engine drives instead of the robot): everything a cycle causes is done
    when it opens, so there is nothing to deliver after a tick."""

    def _participant(self, robot):
        return FusedCycle(self)

    def _deliver(self, engine, cycle) -> None:
        if engine.awaiting():
            cycle.quiescent()
            if engine.awaiting():
                engine.tick(self.clock.now_ns(), quiescent=True)
        if self.bus.pending():
            self.bus.drain()  # anything a node published off the path (none of ours do, mid-episode)


class FusedCycle:
    """The participant the cycle engine drives (``open_cycle``, ``answered``, ``close_cycle``):
    the robot, with every other node's work of the cycle done in between, directly."""

    def __init__(self, cell: FusedCell):
        nodes, bus = cell.nodes, cell.bus
        self.robot = nodes["robot"]
        self.sections = self.robot.sections
        self.sensor = nodes.get("ft_sensor")
        self.teacher = nodes.get("teacher")
        self.estimator = nodes.get("phase_estimator")
        self.commander = nodes.get("impedance_commander")
        self.recorder = nodes.get("recorder")
        self.bus = bus
        self.now = cell.clock.now_ns
        # the subscriptions of the nodes this cycle does not step, by topic ('**': all)
        self.other_nodes = [n for role, n in nodes.items() if role not in STEPPED]
        self.others = {}
        for node in self.other_nodes:
            for sub in node.subscriptions:
                self.others.setdefault(sub.topic, []).append((node.name, sub))
        # ft/wrench's dict is made when a node here reads it (the estimator at its instants, another
        # node's subscription, the bus's check); else its bytes come with only (seq, sent_ns)
        self.wrench_read = bus.check or _WRENCH in self.others or "**" in self.others
        self.recorded: list = []  # the cycle's messages for the recorder, in the order they were made
        self.got: dict[str, int] = {}  # participant -> the seq of its answer this cycle
        self.commands: list = []
        self.hand = None

    # ------------------------------------------------------------- the engine's participant

    def answered(self, names, seq) -> bool:
        got = self.got
        for name in names:
            if got.get(name) != seq:
                return False
        return True

    def open_cycle(self) -> tuple[int, int]:
        robot, commander, teacher, estimator = self.robot, self.commander, self.teacher, self.estimator
        self.got.clear()
        self.commands = []
        self.hand = None
        state = robot.measure_state()
        contact = robot.measure_contact()
        # from here on the other nodes' work on the cycle's messages, the recorder's included:
        # the robot's "wait", as in the per-message engine
        recv = self.now()
        s, c = state[1], contact[1]
        self._record(_STATE, state)
        self._record(_CONTACT, contact)
        tenth = estimator_instant(s["stamp_ns"])
        # the queue's order: robot/state to the commander, the estimator, the teacher;
        # robot/contact to the sensor and the teacher; then what those published
        if commander is not None:
            self._commands(self._work(commander, _STATE, commander.take_state, s, recv))
        phase = None
        if tenth and estimator is not None:
            phase = self._work(estimator, _STATE, estimator.take_state, s)  # None: it waits for the wrench
        hand_on = teacher is not None and teacher.listening
        if hand_on:
            self._work(teacher, _STATE, teacher.take_state, s)
        wrench = None
        if self.sensor is not None:
            read = self.wrench_read or (tenth and estimator is not None)
            wrench = self._work(self.sensor, _CONTACT, self.sensor.sample, c, read)
        hand = self._work(teacher, _CONTACT, teacher.take_contact, c) if hand_on else None
        if wrench is not None:
            self._record(_WRENCH, wrench)
            self.got["ft"] = c["seq"]  # the sensor's record answers the contact's cycle
            if tenth and estimator is not None and phase is None:
                phase = self._work(estimator, _WRENCH, estimator.take_wrench, wrench[1])
        if hand is not None:
            self._record(_HAND, hand)
            self.got["teacher"] = hand[1]["seq"]
            self.hand = (hand[1], self.now())
        if phase is not None:
            self._record(_PHASE, phase)
            self.got["phase"] = phase[1]["seq"]
            if commander is not None:
                self._commands(self._work(commander, _PHASE, commander.take_phase, phase[1]))
        self._hand_to_recorder()
        self.sections.add("wait", self.now() - recv)
        return s["seq"], s["stamp_ns"]

    def quiescent(self) -> None:
        """Everything is delivered and the cycle still waits: as the per-message engine tells
        its nodes (the commander goes on without the estimate; what raises here stops the
        run, as a node's ``quiescent`` does there)."""
        if self.commander is not None:
            self._commands(self.commander.give_up())
            self._hand_to_recorder()
        for node in self.other_nodes:
            node.quiescent()
        if self.bus.pending():
            self.bus.drain()

    def close_cycle(self, stop_on):
        commands = sorted(self.commands, key=lambda e: e[0]) if len(self.commands) > 1 else self.commands
        hand = self.hand
        return self.robot.apply(commands, hand, hand[0] if hand is not None else None, stop_on)

    # ------------------------------------------------------------------------- helpers

    def _commands(self, answers) -> None:
        if answers:
            self.commander.deliver(answers, self._hand_over_command)

    def _hand_over_command(self, topic, payload, message) -> None:
        self._record(topic, (payload, message))
        self.commands.append((message["seq"], (message, self.now())))
        self.got["command"] = message["seq"]

    def _work(self, node, topic, take, *args):
        """A node's work on a message of ``topic``; what it raises is counted as the bus counts
        a handler's (``links`` in its status), and the run goes on."""
        try:
            return take(*args)
        except Exception as exc:  # a bad message must not stop the run
            self.bus.count_bad(node.name, topic, f"{type(exc).__name__}: {exc}")
            return None

    def _record(self, topic, packed) -> None:
        """A message of the cycle: to the others' subscriptions now, to the recorder with the
        rest of the cycle's (``_hand_to_recorder``)."""
        payload, message = packed
        bus, recv = self.bus, self.now()
        if bus.check:
            bus.verify(topic, payload, message)
        self.recorded.append((topic, recv, payload, message))
        if self.others:
            bus.deliver_to(self.others, topic, payload, message, recv)

    def _hand_to_recorder(self) -> None:
        if self.recorded:
            if self.recorder is not None:
                self.recorder.take(self.recorded)
            self.recorded = []
