"""teacher: the simulated human guiding the arm during demonstrations, 1 kHz.

For every robot cycle it reads ``robot/state`` (the measured tcp pose) and
``robot/contact`` (what the hand feels: the contact force and what the tool
touches) and answers on ``teacher/wrench`` with the hand wrench for that
cycle.  Velocities come from differences of consecutive measured poses.
Control: ``reset`` (episode, start, seed, goal_x), ``status``, ``shutdown``.
"""

from __future__ import annotations

import argparse
import sys
import threading
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from robot_sim.teacher import HoseCouplerTeacher, ValleyTeacher
from robot_sim.worlds import Valley, HoseCoupler
from services.runtime.messages import TEACHER_WRENCH
from services.runtime.service import Service, now_ns
from services.runtime.session import ZenohOptions, add_zenoh_arguments, zenoh_options

DT = 0.001


@dataclass(frozen=True)
class TeacherConfig:
    run_id: str
    zenoh: ZenohOptions
    sched_fifo: int = 0  # SCHED_FIFO priority, 0: none
    cpus: tuple = ()  # CPU affinity of the whole process, (): any
    world: str = "valley"


class TeacherProcess:
    def __init__(self, config: TeacherConfig, svc: Service):
        self.config = config
        self.svc = svc
        self.teacher = None
        self.episode = -1
        self._lock = threading.Lock()
        self._states: dict[int, dict] = {}
        self._contacts: dict[int, dict] = {}
        self._prev = None  # (seq, position, rotation)
        self._pub = svc.publisher("teacher/wrench")
        svc.subscribe("robot/state", self.on_state)
        svc.subscribe("robot/contact", self.on_contact)

    def on_state(self, msg, recv_ns, raw):
        with self._lock:
            self._states[msg["seq"]] = msg
            self._try(msg["seq"])

    def on_contact(self, msg, recv_ns, raw):
        with self._lock:
            self._contacts[msg["seq"]] = msg
            self._try(msg["seq"])

    def _try(self, seq):
        if seq not in self._states or seq not in self._contacts:
            return
        state = self._states.pop(seq)
        contact = self._contacts.pop(seq)
        for store in (self._states, self._contacts):  # answers for older cycles are moot now
            for k in [k for k in store if k < seq]:
                del store[k]
        if self.teacher is None or state["episode"] != self.episode:
            return
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
        self._pub.put(TEACHER_WRENCH.encode(seq=seq, stamp_ns=state["stamp_ns"], sent_ns=now_ns(), wrench=hand,
                                            script_phase=int(self.teacher.phase), done=done,
                                            episode=self.episode))

    def reset(self, p: dict) -> None:
        start = np.asarray(p["start"], dtype=np.float64)
        rng = np.random.default_rng(int(p.get("seed", 0)))
        with self._lock:
            if self.config.world == "valley":
                self.teacher = ValleyTeacher(Valley(), start, float(p.get("goal_x", 0.42)), rng)
            else:
                self.teacher = HoseCouplerTeacher(HoseCoupler(), start, rng)
            self.episode = int(p["episode"])
            self._prev = None
            self._states.clear()
            self._contacts.clear()

    def serve(self) -> None:
        self.svc.serve({"reset": self.reset}, status=lambda: {"episode": self.episode})


def main(config: TeacherConfig) -> int:
    with Service("teacher", config.run_id, config.zenoh, sched_fifo=config.sched_fifo,
                 cpus=config.cpus) as svc:
        proc = TeacherProcess(config, svc)
        svc.log(f"ready: world {config.world}")
        proc.serve()
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="etar-teacher", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-id", required=True)
    parser.add_argument("--clock", choices=("lockstep", "realtime"), default="lockstep",
                        help="accepted for symmetry: the teacher answers every robot cycle either way")
    parser.add_argument("--world", choices=("valley", "hose_coupler"), default="valley")
    add_zenoh_arguments(parser)
    return parser


def cli(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return main(TeacherConfig(run_id=args.run_id, zenoh=zenoh_options(args), world=args.world,
                              sched_fifo=args.sched_fifo, cpus=args.cpus))


if __name__ == "__main__":
    sys.exit(cli())
