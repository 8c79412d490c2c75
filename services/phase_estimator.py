"""phase_estimator: the ETAR online forward filter on live data, 100 Hz.

Every tenth robot cycle (10 ms of simulated time) it takes the robot state
and the F/T wrench of that cycle, builds ETAR's state and force vectors
(``services.features``, the same as the learner's) and publishes the
normalised forward message on ``estimator/phase``.  On either clock it waits
for both inputs of the same cycle (the wrench comes through the sensor, a hop
later than the state); a cycle whose wrench has not come by the next tenth
cycle is skipped and counted.  The other nine cycles' messages are not even
decoded (``Service.subscribe(every_tenth=True)``).  On the realtime clock an
estimator that has fallen behind takes the newest tenth cycle and skips the
older ones (``latest=True``: counted as lost), so its estimate is about the
present; lockstep takes every one.
Control: ``reset`` (episode, model path, state, features), ``status``,
``shutdown``.  A wrench with error status or a sample the filter rejects
(non-finite) is skipped and counted; the filter keeps its state.
"""

from __future__ import annotations

import argparse
import sys
import threading
from dataclasses import dataclass

import numpy as np

from etar import ETAR
from services.features import force_vector, pose_of, state_vector
from services.runtime.messages import ESTIMATOR_PHASE
from services.runtime.service import Service, now_ns
from services.runtime.session import ZenohOptions, add_zenoh_arguments, zenoh_options

PERIOD_NS = 10_000_000  # 100 Hz on simulated time, the instants the learner's samples were taken at


@dataclass(frozen=True)
class EstimatorConfig:
    run_id: str
    zenoh: ZenohOptions
    sched_fifo: int = 0  # SCHED_FIFO priority, 0: none
    cpus: tuple = ()  # CPU affinity of the whole process, (): any
    clock: str = "lockstep"
    model: str | None = None


class EstimatorProcess:
    def __init__(self, config: EstimatorConfig, svc: Service):
        self.config = config
        self.svc = svc
        self.model = ETAR.load(config.model) if config.model else None
        self.filter = None
        self.episode = -1
        self.state_kind, self.feature_kind = "position", "force"
        self.R0 = None
        self.skipped = 0
        self.updates = 0
        self._lock = threading.Lock()
        self._states: dict[int, dict] = {}
        self._wrenches: dict[int, dict] = {}
        self._pub = svc.publisher("estimator/phase")
        latest = config.clock == "realtime"
        svc.subscribe("robot/state", self.on_state, every_tenth=True, latest=latest)
        svc.subscribe("ft/wrench", self.on_wrench, every_tenth=True, latest=latest)

    def on_state(self, msg, recv_ns, raw):
        if msg["stamp_ns"] % PERIOD_NS:
            return
        with self._lock:
            # a cycle still waiting for its wrench when the next one comes has lost it
            stale = [k for k in self._states if k < msg["seq"]]
            for k in stale:
                del self._states[k]
            if stale and self.filter is not None:
                self.skipped += len(stale)
            self._states[msg["seq"]] = msg
            self._try(msg["seq"])

    def on_wrench(self, msg, recv_ns, raw):
        if msg["stamp_ns"] % PERIOD_NS:
            return
        with self._lock:
            self._wrenches[msg["seq"]] = msg
            self._try(msg["seq"])

    def _try(self, seq):
        state = self._states.get(seq)
        wrench = self._wrenches.get(seq)
        if state is None or wrench is None:
            return  # wait for the other input of this very cycle
        for store in (self._states, self._wrenches):
            for k in [k for k in store if k <= seq]:
                del store[k]
        if self.filter is None or state["episode"] != self.episode:
            return
        if wrench["status"] != 0:
            self.skipped += 1
            return
        if self.R0 is None:
            self.R0 = pose_of(state["msr_cart_pos"])[0]
        s = state_vector(state["msr_cart_pos"], self.state_kind, self.R0)
        f = force_vector(wrench["wrench"], state["msr_cart_pos"], self.feature_kind)
        try:
            alpha = self.filter.update(s, f)
        except ValueError:
            self.skipped += 1
            return
        self.updates += 1
        self._pub.put(ESTIMATOR_PHASE.encode(seq=seq, stamp_ns=state["stamp_ns"], sent_ns=now_ns(),
                                             posterior=alpha, phase=int(np.argmax(alpha)), input_seq=seq,
                                             ft_seq=wrench["seq"], episode=self.episode))

    def reset(self, p: dict) -> None:
        with self._lock:
            if p.get("model"):
                self.model = ETAR.load(p["model"])
            if self.model is None:
                raise ValueError("no model: pass 'model' (a model file) with reset or --model")
            self.state_kind = p.get("state", "position")
            self.feature_kind = p.get("features", "force")
            self.filter = self.model.filter()
            self.episode = int(p["episode"])
            self.R0 = None
            self._states.clear()
            self._wrenches.clear()
            return {"n_phases": self.model.n_phases}

    def serve(self) -> None:
        self.svc.serve({"reset": self.reset},
                       status=lambda: {"episode": self.episode, "updates": self.updates, "skipped": self.skipped})


def main(config: EstimatorConfig) -> int:
    with Service("phase_estimator", config.run_id, config.zenoh, sched_fifo=config.sched_fifo,
                 cpus=config.cpus) as svc:
        proc = EstimatorProcess(config, svc)
        svc.log(f"ready: clock {config.clock}, model {config.model or '(set by reset)'}")
        proc.serve()
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="etar-phase-estimator", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-id", required=True)
    parser.add_argument("--clock", choices=("lockstep", "realtime"), default="lockstep")
    parser.add_argument("--model", help="learned model file (etar learn --out); can also come with reset")
    add_zenoh_arguments(parser)
    return parser


def cli(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return main(EstimatorConfig(run_id=args.run_id, zenoh=zenoh_options(args), clock=args.clock, model=args.model,
                                sched_fifo=args.sched_fifo, cpus=args.cpus))


if __name__ == "__main__":
    sys.exit(cli())
