"""The KRL program that runs FRI on the KRC: what a lab's remote talks to on the KRL channels.

FRI 1.0 has no start/stop handshake of its own: a KRL program on the KRC calls
``friOpen``, polls the ``$FRI_FRM_*`` values the remote sends, calls ``friStart``
(command mode), ``friStop`` (monitor mode) and ``friClose``, and reports back on
``$FRI_TO_*``.  Each public remote library ships its own program (WIRE.md); this module
runs either, a cycle at a time, against the KRC's :class:`~robot_sim.krc.link.FriLink`:

- ``frilibrary``, the Stanford FRI Library's ``FRIControl.src`` (KRL index = C index + 1):
  ``$FRI_FRM_INT[15]`` strategy, ``$FRI_FRM_INT[16]`` request (10 start, 20 stop, the close
  value to close); ``$FRI_TO_INT[16]`` the program's state (10 open, 20 started, 30
  closed), ``$FRI_TO_INT[15]`` the close value (30, 40 on alternate runs: the program
  loops, opening FRI again after each close).
- ``lwr_hw``, CentroEPiaggio's ``ros_control.src``: ``$FRI_FRM_INT[1]`` strategy,
  ``$FRI_FRM_INT[2]`` 1 start / 0 stop; ``$FRI_TO_INT[2]`` 10 at init, 1 started, 0
  stopped.  It waits for quality PERFECT before ``friStart`` and reports 1 once the
  link is in command mode.

- ``testbench``, the testbench's own runner's: the runner sets the modes (the episode
  protocol, as over Zenoh) and the program leaves the channels to the run: the KRC
  reports the episode on ``$FRI_TO_*`` and the remote, the testbench's commander, its
  goal and holds on ``$FRI_FRM_*`` (``services/nodes/robot.py`` says which index holds
  what).

The public ones use the strategy numbers 10 joint position, 20 Cartesian impedance, 30 joint
impedance; anything else (90 joint torque, ...) is refused: the program stays in monitor
mode and says why in :attr:`KrlProgram.refusal`, in its event list and in
``$FRI_TO_INT[14]`` (the testbench's own channel: the refused strategy's number, 0 when
nothing is refused; neither public program uses index 14).

The program polls every ``POLL_S`` (50 ms, FRIControl.src's ``WAIT SEC 0.05``), so a
request takes effect at the next poll, as on a real KRC.  ``friStart`` returns once
the link has entered command mode (it needs quality PERFECT for a while, FriLink's
rule), and the program reports "started" then.  A close ends the session: the KRC goes
on sending measurements with state OFF for ``OFF_STREAM_S`` (the Stanford remote
waits for packets after closing and hangs if the KRC falls silent at once; WIRE.md),
then opens FRI again (``frilibrary``) for the next run of the remote.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from robot_sim.cycle import FRI_RATE_HZ
from robot_sim.krc.link import FriLink
from robot_sim.krc.packets import ControlMode, FriQuality, FriState

__all__ = ["KRL_CONVENTIONS", "LAB_CONVENTIONS", "OFF_STREAM_S", "POLL_S", "REFUSAL_INDEX", "STRATEGIES", "KrlEvent", "KrlProgram"]

KRL_CONVENTIONS = ("frilibrary", "lwr_hw", "testbench")
LAB_CONVENTIONS = ("frilibrary", "lwr_hw")  # the public remotes' (etar-bench serve)
POLL_S = 0.05
OFF_STREAM_S = 1.0
REFUSAL_INDEX = 14  # $FRI_TO_INT[14]: the strategy refused (the testbench's own channel)

# strategy number -> the control mode it selects (both public conventions number them so)
STRATEGIES = {10: ControlMode.POSITION, 20: ControlMode.CART_IMP, 30: ControlMode.JNT_IMP}
_STRATEGY_NAMES = {10: "joint position", 20: "Cartesian impedance", 30: "joint impedance", 40: "joint effort",
                   50: "joint stiffness", 90: "joint torque"}

# frilibrary (FRIControl.src)
_FL_STRATEGY, _FL_REQUEST = 15, 16  # $FRI_FRM_INT[..]
_FL_CLOSE_VALUE, _FL_STATE = 15, 16  # $FRI_TO_INT[..]
FL_START, FL_STOP = 10, 20
FL_OPEN, FL_STARTED, FL_CLOSED = 10, 20, 30
# lwr_hw (ros_control.src)
_LH_STRATEGY, _LH_REQUEST = 1, 2
_LH_STATE = 2
LH_INIT, LH_STARTED, LH_STOPPED = 10, 1, 0


@dataclass(frozen=True)
class KrlEvent:
    """What the program did at cycle ``seq``: ``kind`` (open, start, started, stop,
    close, off, refused) and a sentence."""

    seq: int
    kind: str
    text: str


class KrlProgram:
    """One of the public KRL programs, run once per FRI cycle by :meth:`step`.

    ``switch_mode(mode) -> bool`` changes the KRC's control mode (the cell's, which
    tells the link and the law); ``supported``: the control modes the KRC can run.
    :attr:`krl_to` is what goes out in every measurement's KRL block.
    """

    def __init__(self, convention: str, link: FriLink, switch_mode, *,
                 supported=(ControlMode.POSITION, ControlMode.CART_IMP, ControlMode.JNT_IMP),
                 cycle_hz: int = FRI_RATE_HZ):
        if convention not in KRL_CONVENTIONS:
            raise ValueError(f"krl must be one of {', '.join(KRL_CONVENTIONS)}, got {convention!r}")
        self.convention = convention
        self.link = link
        self.switch_mode = switch_mode
        self.supported = frozenset(ControlMode(m) for m in supported)
        self.poll_cycles = max(1, round(POLL_S * cycle_hz))
        self.off_cycles = max(1, round(OFF_STREAM_S * cycle_hz))
        self.krl_to = KrlChannels()
        self.events: list[KrlEvent] = []
        self.refusal = ""
        self.runs = 0  # FRI sessions opened
        self._k = 0
        self._starting = False  # friStart called, command mode not entered yet
        self._started = False
        self._off_left = 0  # cycles of OFF streaming left after a close
        self._close_value = 30
        self._refused = None
        self._open(0)

    # ----------------------------------------------------------------- read-outs
    @property
    def streaming_off(self) -> bool:
        """Closed: the measurements go out with state OFF until FRI is opened again."""
        return self._off_left > 0

    @property
    def started(self) -> bool:
        return self._started

    # ------------------------------------------------------------------- cycle
    def step(self, seq: int, krl_from: KrlChannels | None) -> None:
        """One FRI cycle (``seq``, the measurement just sent) with the newest ``$FRI_FRM_*``."""
        self._k += 1
        if self._off_left:
            self._off_left -= 1
            if self._off_left == 0:
                self._open(seq)
            return
        if self._starting and self.link.state == FriState.CMD:
            self._starting, self._started = False, True
            self._report(LH_STARTED if self.convention == "lwr_hw" else FL_STARTED)
            self._event(seq, "started", "friStart: command mode entered")
        if self._started and self.link.state != FriState.CMD:
            # the link fell back to monitor mode (quality below OK): the program's friStart ended
            self._started = False
            self._event(seq, "fallback", f"command mode left: quality {self.link.quality.name}")
            self._report(LH_STOPPED if self.convention == "lwr_hw" else FL_OPEN)
        if self._k % self.poll_cycles or krl_from is None:
            return
        if self.convention == "frilibrary":
            self._poll_frilibrary(seq, krl_from)
        elif self.convention == "lwr_hw":
            self._poll_lwr_hw(seq, krl_from)
        # testbench: the runner starts and stops command mode itself

    # ------------------------------------------------------------ conventions
    def _poll_frilibrary(self, seq: int, frm: KrlChannels) -> None:
        request = int(frm.ints[_FL_REQUEST - 1])
        if request == self._close_value:
            self._close(seq)
        elif request == FL_START and not (self._started or self._starting):
            self._start_once(seq, request, int(frm.ints[_FL_STRATEGY - 1]))
        elif request == FL_STOP and (self._started or self._starting):
            self._stop(seq)
            self._report(FL_OPEN)

    def _start_once(self, seq: int, request: int, strategy: int) -> None:
        # a refused start is not tried again at every poll: only when the remote changes
        # its request or its strategy
        if self.refusal and (request, strategy) == self._refused:
            return
        self._start(seq, strategy)
        self._refused = (request, strategy) if self.refusal else None

    def _poll_lwr_hw(self, seq: int, frm: KrlChannels) -> None:
        request = int(frm.ints[_LH_REQUEST - 1])
        if request == 1 and not (self._started or self._starting):
            if self.link.quality != FriQuality.PERFECT:
                return  # ros_control.src waits for PERFECT before friStart
            self._start_once(seq, request, int(frm.ints[_LH_STRATEGY - 1]))
        elif request == 0 and (self._started or self._starting):
            self._stop(seq)
            self._report(LH_STOPPED)

    # ----------------------------------------------------------------- actions
    def _start(self, seq: int, strategy: int) -> None:
        mode = STRATEGIES.get(strategy)
        name = _STRATEGY_NAMES.get(strategy, "unknown")
        if mode is None or mode not in self.supported:
            self.refusal = (f"strategy {strategy} ({name}) refused: the simulated KRC runs "
                            + ", ".join(f"{s} ({_STRATEGY_NAMES[s]})" for s, m in STRATEGIES.items()
                                        if m in self.supported))
            self.krl_to.ints[REFUSAL_INDEX - 1] = strategy
            self._event(seq, "refused", self.refusal)
            return
        self.refusal = ""
        self.krl_to.ints[REFUSAL_INDEX - 1] = 0
        if self.link.control_mode != mode:
            self.switch_mode(mode)
        self.link.request_command_mode()
        self._starting = True
        self._event(seq, "start", f"friStart with strategy {strategy} ({name})")

    def _stop(self, seq: int) -> None:
        self.link.request_monitor_mode()
        self._starting = self._started = False
        self._event(seq, "stop", "friStop: monitor mode")

    def _close(self, seq: int) -> None:
        if self._started or self._starting:
            self._stop(seq)
        self._report(FL_CLOSED)
        self._off_left = self.off_cycles
        self._event(seq, "close", f"friClose: streaming OFF for {OFF_STREAM_S:g} s, then FRI opens again")

    def _open(self, seq: int) -> None:
        self.runs += 1
        self._starting = self._started = False
        if self.convention == "frilibrary":
            # FRIControl.src alternates the close value so a stale close of the last run
            # cannot close this one
            self._close_value = 30 if self.runs % 2 else 40
            self.krl_to.ints[_FL_CLOSE_VALUE - 1] = self._close_value
            self._report(FL_OPEN)
        elif self.convention == "lwr_hw":
            self._report(LH_INIT)
        self._event(seq, "open", "friOpen: monitor mode")

    def _report(self, value: int) -> None:
        if self.convention == "testbench":
            return  # the channels are the run's
        index = _FL_STATE if self.convention == "frilibrary" else _LH_STATE
        self.krl_to.ints[index - 1] = value

    def _event(self, seq: int, kind: str, text: str) -> None:
        self.events.append(KrlEvent(int(seq), kind, text))


# testbench: what the run's KRC and its remote (the testbench's commander) tell each other
# on the KRL channels, beside the FRI fields (KRL indices, from 1)
TB_EPISODE, TB_KIND = 1, 2  # $FRI_TO_INT: the episode index (-1: none), its kind (TB_KINDS)
TB_KINDS = ("none", "demonstration", "reproduction", "served")
TB_GRAVITY_COMPENSATION = 1  # $FRI_TO_BOOL: the KRC runs gravity compensation (teaching)
TB_GOAL_REACHED = 1  # $FRI_FRM_BOOL: the remote has reached its goal
TB_HOLD, TB_ESTIMATE_SEQ = 1, 2  # $FRI_FRM_INT: why it holds (TB_HOLDS), the estimate it used (-1: none)
TB_HOLDS = ("", "stale_estimate", "wrench_saturated", "wrench_invalid", "other")


KRL_SIZE = 16  # values of each kind in a KRL block


@dataclass(slots=True, eq=False)
class KrlChannels:
    """One direction's KRL block: ``$FRI_TO_*`` (KRC -> remote, in the measurement) or
    ``$FRI_FRM_*`` (remote -> KRC, in the command).

    KRL counts from 1: ``$FRI_TO_INT[16]`` is ``ints[15]``; ``$FRI_TO_BOOL[i]`` is bit
    ``i - 1`` of ``bools`` (use :meth:`flag` / :meth:`set_flag` with the KRL index).
    Reals cross as float32, integers as int32.
    """

    reals: np.ndarray = field(default_factory=lambda: np.zeros(KRL_SIZE))
    ints: np.ndarray = field(default_factory=lambda: np.zeros(KRL_SIZE, dtype=np.int64))
    bools: int = 0

    def flag(self, krl_index: int) -> bool:
        """``$FRI_..._BOOL[krl_index]`` (1..16)."""
        return bool(self.bools >> (_krl_index(krl_index) - 1) & 1)

    def set_flag(self, krl_index: int, value: bool) -> None:
        bit = 1 << (_krl_index(krl_index) - 1)
        self.bools = (self.bools | bit) if value else (self.bools & ~bit)

    def copy(self) -> KrlChannels:
        return KrlChannels(np.array(self.reals, dtype=np.float64), np.array(self.ints, dtype=np.int64),
                           int(self.bools))


def _krl_index(i: int) -> int:
    if not 1 <= int(i) <= KRL_SIZE:
        raise ValueError(f"KRL index {i} outside 1..{KRL_SIZE}")
    return int(i)
