"""The robot's inbox: the participants' answers to its FRI cycles (``robot/command``,
``ft/wrench``, ``estimator/phase``, ``teacher/wrench``), stored by the cycle they answer
as they arrive on transport threads while the cycle engine's thread closes cycles."""

from __future__ import annotations

import threading

_KEEP = 4000  # answers kept per participant: memory stays bounded on long realtime runs


class AnswerInbox:
    """Answers by participant and cycle.

    ``awaited``: the participants the episode in progress waits for; another's answer is
    stored but wakes nobody (over Zenoh the sensor's answer to every cycle of a
    demonstration woke the engine's thread for nothing, a context switch a cycle).
    ``arrivals`` is bumped with every awaited answer: a transport waits on ``arrived``
    for it to change."""

    def __init__(self, participants):
        self.arrived = threading.Condition()
        self.arrivals = 0
        self.awaited: frozenset = frozenset(participants)
        self._answers: dict[str, dict] = {name: {} for name in participants}
        self._latest_teacher = None

    def handler(self, name):
        """What the transport calls with each answer of participant ``name``."""
        store = self._answers[name]

        def on_answer(msg, recv_ns, raw):
            with self.arrived:
                store[msg["seq"]] = (msg, recv_ns)
                if len(store) > _KEEP:
                    for k in sorted(store)[:_KEEP // 2]:
                        del store[k]
                if name == "teacher":
                    self._latest_teacher = msg
                if name in self.awaited:
                    self.arrivals += 1
                    self.arrived.notify_all()
        return on_answer

    def has(self, names, seq) -> bool:
        """Have all of ``names`` answered cycle ``seq``?"""
        answers = self._answers
        for n in names:
            if seq not in answers[n]:
                return False
        return True

    def take(self, seq: int):
        """(every command that came since the last take, by seq: this cycle's and late ones
        for cycles already closed, which the FRI link must see to count them late; the
        teacher's answer to ``seq`` or None; the newest teacher message)."""
        with self.arrived:
            commands = self._answers["command"]
            entries = sorted(commands.items()) if commands else ()
            commands.clear()
            return entries, self._answers["teacher"].pop(seq, None), self._latest_teacher

    def clear(self) -> None:
        with self.arrived:
            for store in self._answers.values():
                store.clear()
