"""The phase_estimator node: the ETAR online forward filter on live data, 100 Hz.

Every tenth robot cycle (10 ms of simulated time) it takes the robot state and
the F/T wrench of that cycle, builds ETAR's state and force vectors
(``etar.features``, the same as the learner's) and publishes the
normalised forward message on ``estimator/phase``.  It waits for both inputs of
the same cycle (the wrench comes through the sensor, a hop later than the
state); a cycle whose wrench has not come by the next tenth cycle is skipped and
counted.  The other nine cycles' messages are not even decoded
(``every_tenth``); realtime takes the newest tenth cycle (``latest``).
Control: ``reset`` (episode, model file; state and features default to the
task's; ``resync``: the filter joins a reproduction under way, every phase
equally likely at first, as after a restart).  A wrench with error status or a
sample the filter rejects (non-finite) is skipped and counted; the filter keeps
its state.  A step the phase's law did not drive - the KRC in monitor mode at
one of its ends (it holds the arm), or its first sample skipped or missing - is
not conditioned on: its last sample only starts the next step, the posterior
stays, and the estimate says why (``unconditioned``), so the estimate after a
hold continues from the phase before it.  A wrench the sensor flags (saturated, non-finite input) is a fault
the commander must act on at once: the estimate of that cycle is still
published, with the last posterior and ``input_fault`` saying why it did not
move.  A wrench that never comes shows as estimates that stop (the commander's
stale-estimate hold).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from etar.task import load_task
from etar.features import force_vector, pose_of, state_vector
from robot_sim.wire.fri_udp import host_port
from services.runtime.bus import Node, Publication, Subscription
from services.runtime.config import option
from robot_sim.krc.packets import FriState
from robot_sim.ati.rdt import AtiStatus
from services.runtime.messages import (ESTIMATOR_PERIOD_NS, ESTIMATOR_PHASE, FT_WRENCH, ROBOT_STATE,
                                       estimator_instant)

_SATURATED = int(AtiStatus.FT_OUT_OF_RANGE)
_COMMAND_MODE = int(FriState.CMD)



@dataclass(frozen=True)
class EstimatorConfig:
    model: str | None = option(None, "learned model file (etar learn --out); can also come with reset",
                               metavar="FILE")
    mute_after: float = option(0.0, "fault injection: publish no estimate after S seconds of each "
                                    "reproduction (simulated time; 0: never)", metavar="S")
    netft: str = option("", "read the wrench from a Net F/T box's RDT stream at this address instead of "
                            "ft/wrench (realtime)", metavar="HOST:PORT")
    netft_http_port: int = option(80, "--netft: the box's HTTP port (its calibration, /netftapi2.xml)",
                                  metavar="PORT")

    def __post_init__(self):
        if not (math.isfinite(self.mute_after) and self.mute_after >= 0):
            raise ValueError(f"mute_after must be a finite number of seconds >= 0, got {self.mute_after!r}")
        if self.netft:
            host_port(self.netft, "netft")
        if isinstance(self.netft_http_port, bool) or not 1 <= self.netft_http_port <= 65535:
            raise ValueError(f"netft_http_port must be a port 1..65535, got {self.netft_http_port!r}")


class PhaseEstimatorNode(Node):
    name = "phase_estimator"

    def __init__(self, config: EstimatorConfig, bus, clock, *, run_id: str = "", mode: str = "lockstep",
                 netft_stream=None, **_):
        super().__init__(bus, clock)
        self.task = load_task(config.model) if config.model else None
        self.mute_after_ns = int(config.mute_after * 1e9)
        self.muted = 0  # estimates left unpublished by the injected fault
        self._t0 = None  # the episode's first estimated instant
        self.filter = None
        self.episode = -1
        self.state_kind, self.feature_kind = "position", "force"
        self.state_resolution = 0.0
        self.R0 = None
        self.skipped = 0
        self.updates = 0
        self.input_faults = 0  # estimates published with input_fault
        self.unconditioned = {"arm_held": 0, "gap": 0}  # samples taken without conditioning on their step
        self._last = None  # (stamp_ns, in command mode) of the filter's newest sample
        self._alpha = None  # the last posterior the filter gave
        self._lock = threading.Lock()
        self._states: dict[int, dict] = {}
        self._wrenches: dict[int, dict] = {}
        self.publications = [Publication(ESTIMATOR_PHASE.topic)]
        self.subscriptions = [Subscription(ROBOT_STATE.topic, self.on_state, every_tenth=True, latest=True)]
        self.netft = None
        if config.netft:
            if mode == "lockstep":
                raise ValueError("netft needs the realtime clock: the box streams on the sensor's own clock")
            if netft_stream is None:
                raise ValueError("netft: the service process brings the Net F/T client (services.transport.lab)")
            self.netft = netft_stream(lambda msg, recv_ns: self.on_wrench(msg, recv_ns, None))
        else:
            self.subscriptions.append(Subscription(FT_WRENCH.topic, self.on_wrench, every_tenth=True, latest=True))

    @property
    def listening(self) -> bool:
        return self.filter is not None  # before its first reproduction it has nothing to estimate

    def on_state(self, msg, recv_ns, raw):
        if estimator_instant(msg["stamp_ns"]):
            with self._lock:
                self._publish(self.take_state(msg))

    def on_wrench(self, msg, recv_ns, raw):
        if estimator_instant(msg["stamp_ns"]):
            with self._lock:
                self._publish(self.take_wrench(msg))

    def _publish(self, packed) -> None:
        if packed is not None:
            self.bus.publish(ESTIMATOR_PHASE.topic, *packed)

    # an estimator instant's inputs: the estimate once both are in, ``estimator/phase`` as
    # ``pack`` gives it, or None.  Unlocked: the handlers above hold the lock; an engine that
    # steps the nodes itself (services.transport.fused) calls them from its one thread

    def take_state(self, msg):
        # a cycle still waiting for its wrench when the next one comes has lost it
        stale = [k for k in self._states if k < msg["seq"]]
        for k in stale:
            del self._states[k]
        if stale and self.filter is not None:
            self.skipped += len(stale)
        self._states[msg["seq"]] = msg
        return self._try(msg["seq"])

    def take_wrench(self, msg):
        self._wrenches[msg["seq"]] = msg
        return self._try(msg["seq"])

    def _try(self, seq):
        state = self._states.get(seq)
        wrench = self._wrenches.get(seq)
        if state is None or wrench is None:
            return None  # wait for the other input of this very cycle
        for store in (self._states, self._wrenches):
            for k in [k for k in store if k <= seq]:
                del store[k]
        if self.filter is None or state["episode"] != self.episode:
            return None
        fault = unconditioned = None
        if wrench["status"] != 0:
            self.skipped += 1
            fault = "wrench_saturated" if wrench["status"] & _SATURATED else "wrench_invalid"
            self.input_faults += 1
            alpha = self._alpha
            if alpha is None:  # nothing estimated yet: no phase is more likely than another
                alpha = np.full(self.task.n_phases, 1.0 / self.task.n_phases)
        else:
            if self.R0 is None:
                self.R0 = pose_of(state["msr_cart_pos"])[0]
            s = state_vector(state["msr_cart_pos"], self.state_kind, self.R0, self.state_resolution)
            f = force_vector(wrench["wrench"], state["msr_cart_pos"], self.feature_kind)
            # the AR emission of a step holds only where the phase's own law drove the arm
            # from one sample to the next: not across a KRC hold (monitor mode), not across
            # a missing sample; there the sample only starts the next step
            commanded = state["fri_state"] == _COMMAND_MODE
            last = self._last
            if last is None or state["stamp_ns"] - last[0] != ESTIMATOR_PERIOD_NS:
                unconditioned = "gap" if last is not None else None
            elif not (commanded and last[1]):
                unconditioned = "arm_held"
            else:
                unconditioned = None
            try:
                alpha = self.filter.anchor(s, f) if unconditioned else self.filter.update(s, f)
            except ValueError:
                self.skipped += 1
                return None
            self._last = (state["stamp_ns"], commanded)
            if unconditioned:
                self.unconditioned[unconditioned] += 1
            else:
                self.updates += 1
            self._alpha = alpha
        if self._t0 is None:
            self._t0 = state["stamp_ns"]
        if self.mute_after_ns and state["stamp_ns"] - self._t0 >= self.mute_after_ns:
            self.muted += 1
            return None
        return ESTIMATOR_PHASE.pack(
            seq=seq, stamp_ns=state["stamp_ns"], sent_ns=self.clock.now_ns(), posterior=alpha,
            phase=int(np.argmax(alpha)), input_seq=seq, ft_seq=wrench["seq"], episode=self.episode,
            **({"input_fault": fault} if fault else {}),
            **({"unconditioned": unconditioned} if unconditioned else {}))

    def handlers(self):
        return {"reset": self.reset}

    def reset(self, p: dict) -> dict:
        task = load_task(p["model"]) if p.get("model") else self.task
        if task is None:
            raise ValueError("no model: pass 'model' (a model file) with reset or --model")
        # the filter's compiled step is loaded on first use, which can take seconds on a
        # busy machine: here, not at the first sample of the episode, where a lockstep
        # commander waiting for the estimate went on without it (once three times in a row)
        warm = task.model.filter()
        try:
            for _ in range(2):
                warm.update(np.zeros(task.model.n_state), np.zeros(task.model.n_force))
        except ValueError:
            pass  # a sample this model finds impossible: the kernel is loaded all the same
        with self._lock:
            self.task = task
            self.state_kind = p.get("state", task.state)
            self.feature_kind = p.get("features", task.features)
            self.state_resolution = task.state_resolution
            # resync: a restarted estimator joins the reproduction under way, where the
            # learned prior of the task's first phase would be wrong
            self.filter = task.model.filter(start="uniform" if p.get("resync") else "first")
            self.episode = int(p["episode"])
            self.R0 = None
            self._t0 = None
            self._alpha = None
            self._last = None
            self._states.clear()
            self._wrenches.clear()
        return {"n_phases": task.n_phases}

    def status(self) -> dict:
        status = {"episode": self.episode, "updates": self.updates, "skipped": self.skipped,
                  "input_faults": self.input_faults, "muted": self.muted,
                  "unconditioned": dict(self.unconditioned)}
        if self.netft is not None:
            status["netft"] = self.netft.status()
        return status

    def close(self) -> None:
        if self.netft is not None:
            self.netft.close()
