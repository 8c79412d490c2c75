"""The teacher node: the simulated human guiding the arm during demonstrations.

For every robot cycle it reads ``robot/state`` and ``robot/contact`` (what the
hand feels: the tool's true pose and velocity, the contact force and what the
tool touches) and answers on ``teacher/wrench`` with the hand wrench for that
cycle (``robot_sim.world.teacher``).  Control: ``reset`` (episode, start, seed, goal_x), ``idle`` (the
demonstration is over: answer nothing until the next reset).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from robot_sim.cycle import FRI_CYCLE_NS
from robot_sim.world.teacher import HoseCouplerTeacher, ValleyTeacher
from robot_sim.world.tasks import HoseCoupler, TASK_WORLDS, Valley
from services.runtime.bus import Node, Publication, Subscription
from services.runtime.config import option
from services.runtime.messages import ROBOT_CONTACT, ROBOT_STATE, TEACHER_WRENCH

DT = FRI_CYCLE_NS / 1e9  # the hand answers every FRI cycle


@dataclass(frozen=True)
class TeacherConfig:
    world: str = option("valley", "task world", choices=TASK_WORLDS)

    def __post_init__(self):
        if self.world not in TASK_WORLDS:
            raise ValueError(f"world must be one of {', '.join(TASK_WORLDS)}, got {self.world!r}")


class TeacherNode(Node):
    name = "teacher"

    def __init__(self, config: TeacherConfig, bus, clock, **_):
        super().__init__(bus, clock)
        self.config = config
        self.teacher = None
        self.episode = -1
        self._lock = threading.Lock()
        self._states: dict[int, dict] = {}
        self._contacts: dict[int, dict] = {}
        self._prev = None  # (seq, position, rotation)
        self.publications = [Publication(TEACHER_WRENCH.topic)]
        # realtime: a hand reacts to the arm as it is now, not to a backlog
        self.subscriptions = [Subscription(ROBOT_STATE.topic, self.on_state, latest=True),
                              Subscription(ROBOT_CONTACT.topic, self.on_contact, latest=True)]

    def on_state(self, msg, recv_ns, raw):
        with self._lock:
            self._publish(self.take_state(msg))

    def on_contact(self, msg, recv_ns, raw):
        with self._lock:
            self._publish(self.take_contact(msg))

    def _publish(self, packed) -> None:
        if packed is not None:
            self.bus.publish(TEACHER_WRENCH.topic, *packed)

    # the hand's answer once both of a cycle's messages are in: ``teacher/wrench`` as ``pack``
    # gives it, or None.  Unlocked: the handlers above hold the lock; an engine that steps
    # the nodes itself (services.transport.fused) calls them from its one thread

    def take_state(self, msg):
        self._states[msg["seq"]] = msg
        return self._try(msg["seq"])

    def take_contact(self, msg):
        self._contacts[msg["seq"]] = msg
        return self._try(msg["seq"])

    def _try(self, seq):
        if seq not in self._states or seq not in self._contacts:
            return None
        state = self._states.pop(seq)
        contact = self._contacts.pop(seq)
        for store in (self._states, self._contacts):  # answers for older cycles are moot now
            if store:
                for k in [k for k in store if k < seq]:
                    del store[k]
        if self.teacher is None or state["episode"] != self.episode:
            return None
        true_pose, twist = contact.get("tcp_pose"), contact.get("tcp_twist")
        if true_pose is not None and twist is not None:
            # the hand holds the tool: it feels its true motion, not the KRC's measurement
            # (whose 20 um of joint noise, differenced over 1 ms, made the hand's damping
            # shake the arm by ~2 N at every cycle)
            pose = np.asarray(true_pose).reshape(3, 4)
            x, R = pose[:, 3], pose[:, :3]
            v, w = np.asarray(twist[:3]), np.asarray(twist[3:])
        else:  # a robot of an earlier version: the measured pose, differenced
            pose = np.asarray(state["msr_cart_pos"]).reshape(3, 4)
            x, R = pose[:, 3], pose[:, :3]
            if self._prev is not None and self._prev[0] == seq - 1:
                v = (x - self._prev[1]) / DT
                w = R @ pin.log3(self._prev[2].T @ R) / DT
            else:
                v = np.zeros(3)
                w = np.zeros(3)
            self._prev = (seq, x.copy(), R.copy())
        hand = self.teacher.step(DT, x, v, R, w, np.asarray(contact["contact_force"]), contact["touching"])
        done = bool(self.teacher.done)
        if isinstance(self.teacher, HoseCouplerTeacher):
            done = self.teacher.phase == 1 and self.teacher.rotation_done(R)
        return TEACHER_WRENCH.pack(
            seq=seq, stamp_ns=state["stamp_ns"], sent_ns=self.clock.now_ns(), wrench=hand,
            script_phase=int(self.teacher.phase), done=done, episode=self.episode)

    @property
    def listening(self) -> bool:
        return self.teacher is not None

    def handlers(self):
        return {"reset": self.reset, "idle": self.idle_until_reset}

    def idle_until_reset(self, p: dict) -> None:
        """The demonstration is over: answer nothing until the next reset (a reproduction
        whose index equals a demonstration's must not be answered, nor cost the work)."""
        with self._lock:
            self.teacher = None
            self.episode = -1
            self._prev = None

    def reset(self, p: dict) -> None:
        start = np.asarray(p["start"], dtype=np.float64)
        if start.shape != (3,) or not np.all(np.isfinite(start)):
            raise ValueError(f"start must be 3 finite numbers, got {p['start']!r}")
        rng = np.random.default_rng(int(p.get("seed", 0)))
        with self._lock:
            if self.config.world == "valley":
                self.teacher = ValleyTeacher(Valley(), start, float(p.get("goal_x", Valley.goal_x)), rng)
            else:
                self.teacher = HoseCouplerTeacher(HoseCoupler(), start, rng)
            self.episode = int(p["episode"])
            self._prev = None
            self._states.clear()
            self._contacts.clear()

    def status(self) -> dict:
        return {"episode": self.episode}
