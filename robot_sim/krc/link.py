"""The KUKA FRI 1.0 link as the KRC (robot controller) sees it.

What is modelled
----------------
The KRC sends one *measurement* packet per FRI cycle (1-100 ms, 1 ms here by
default) and expects the remote side to answer it with a *command* packet that
echoes the measurement's sequence number before the cycle ends.  This module
keeps the KRC's books on that exchange and decides what the controller applies
each cycle.  It is pure logic: no sockets, no physics, no threads and no clock.
Every call takes the time as an integer number of nanoseconds, so a test (or
the lockstep clock) can drive it with synthetic times.

- Sequence numbers.  Each measurement gets the next ``seq`` (the first one
  after construction is 1, so a default-initialised echo of 0 never matches).
  ``seq`` keeps counting across ``stop()``/``start()`` so that a stale answer
  from an earlier session can never pass for a current one.
  ``reflected_seq`` is the echo of the most recent well-formed command packet
  that reached the KRC in this session (in time or late), -1 if none yet.
- Deadline.  The answer to measurement ``seq`` sent at ``t`` is *in time* only
  if it arrives at ``t_arrival < t + cycle`` while ``seq`` is still the current
  cycle.  Answers to older seqs or arriving at/after the deadline are counted
  as *late* and ignored; packets failing ``CommandPacket.is_valid`` (or echoing
  a seq that was never sent, or arriving before their measurement was sent) are
  counted as *corrupt* and ignored; a second in-time answer to the same seq is
  counted as a *duplicate* and ignored (the first one wins).  A cycle without
  an accepted in-time answer is *missed*.  Bad packets never raise.
- Statistics over the last ``window`` (100) closed cycles: answer rate
  (in-time answers / cycles), miss rate (1 - answer rate), mean latency and
  jitter (population standard deviation of latency).  Latency is
  ``arrival - send time`` of the measurement answered and is recorded for every
  well-formed answer whose cycle is still in the window, late ones included:
  the latency figures describe the link, the miss rate describes the deadline.
  Latencies are kept as integer nanoseconds, so the sums are exact.
  With no closed cycle yet all four figures are 0.0; with no latency in the
  window the latency and jitter are 0.0 (0.0 rather than NaN keeps the
  published messages valid JSON).
- Quality, computed at every ``end_cycle`` from the packets in the window.  At
  start-up the window is short: quality is judged on the closed cycles seen so
  far (one missed cycle out of three is 33 %), and with none it is
  UNACCEPTABLE (nothing is known about the link yet).  Defaults
  (``FriConfig`` fields in brackets):

  ============  ==========================================================
  PERFECT       no miss in the window, mean latency < 0.5 cycle
                [perfect_max_latency_cycles] and jitter < 0.25 cycle
                [perfect_max_jitter_cycles]
  OK            miss rate <= 2 % [ok_max_miss_rate]
  BAD           miss rate <= 10 % [bad_max_miss_rate]
  UNACCEPTABLE  anything worse
  ============  ==========================================================

- States.  OFF -> MON on ``start()``.  MON -> CMD at the end of a cycle once
  ``request_command_mode()`` has been called and quality has been PERFECT for
  ``perfect_hold_cycles`` consecutive closed cycles (the run is counted whether
  or not a request is pending, so a request on a link that has long been
  PERFECT takes effect at the next ``end_cycle``).  CMD -> MON when quality
  falls below OK (the request is cleared: a new ``request_command_mode()`` is
  needed) or on ``request_monitor_mode()``.  Any state -> OFF on ``stop()``.
- What is applied (``CycleOutcome``).  In OFF and MON: no command, hold the
  pose.  In CMD: the cycle's accepted answer; if it is missing and at most
  ``max_bridged_misses`` consecutive cycles are missing, the last command
  applied in this CMD session is repeated (``bridged``); more consecutive
  misses, or no command applied yet in this CMD session, mean hold.  A command
  whose ``requested_mode`` differs from the KRC's control mode is not applied
  either (hold; counted as ``mode_mismatch``): the transport worked, so it
  does not count as a miss.
- Control mode (POSITION / CART_IMP / JNT_IMP) is switched by the KRC side with
  ``switch_control_mode`` and only in MON, as in FRI 1.0.
- Faults (``LinkFaults``): delay, uniform jitter, loss, corruption,
  duplication and reordering of command packets, and loss of measurement
  packets, from an explicit seed, optionally only within a window of time.

Order of calls per cycle
------------------------
::

    m = link.measurement(t, q, x, wrench)      # KRC sends; cycle seq m.seq opens
    m = link.deliver_measurement(m)            # optional: None if the fault hook lost it
    link.receive(cmd, t_arrival)               # remote's answer (or link.deliver(cmd, t_sent))
    out = link.end_cycle(t + link.config.cycle_ns)   # KRC closes the cycle, applies out.command

``receive`` may be called for any arrival time: the arrival time, not the order
of calls, decides whether an answer is in time, so a fault hook can hand over a
delayed packet at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from kernel_plumbing.addresses import HoldsAddresses, address, int64_address
from robot_sim.cycle import FRI_CYCLE_NS
from robot_sim.krc import link_books as lb
from robot_sim.krc.faults import LinkFaults
from robot_sim.krc.packets import (_CART, _FT, _JNT, CommandPacket, ControlMode, FriQuality, FriState,
                                   CommandChecks, MeasurementPacket, checked_in_place, command_problem,
                                   control_mode_or_value, is_integer)

@dataclass(frozen=True)
class FriConfig:
    """Timing, window and quality thresholds of the link.

    Quality thresholds (see the module docstring):
    PERFECT needs no miss in the window, mean latency below
    ``perfect_max_latency_cycles`` cycles and jitter below
    ``perfect_max_jitter_cycles`` cycles; OK needs miss rate <=
    ``ok_max_miss_rate``; BAD needs miss rate <= ``bad_max_miss_rate``;
    anything worse is UNACCEPTABLE.
    """

    cycle_ns: int = FRI_CYCLE_NS  # FRI 1.0 allows 1..100 ms
    window: int = 100  # packets the statistics and quality are taken over
    perfect_hold_cycles: int = 500  # consecutive PERFECT cycles before MON -> CMD
    perfect_max_latency_cycles: float = 0.5
    perfect_max_jitter_cycles: float = 0.25
    ok_max_miss_rate: float = 0.02
    bad_max_miss_rate: float = 0.10
    max_bridged_misses: int = 1  # consecutive missing answers covered by repeating the last command
    initial_control_mode: ControlMode = ControlMode.CART_IMP  # the testbench runs Cartesian impedance

    def __post_init__(self):
        def need(ok: bool, name: str, what: str):
            if not ok:
                raise ValueError(f"FriConfig.{name} = {getattr(self, name)!r}: {what}")

        need(is_integer(self.cycle_ns), "cycle_ns", "must be an integer number of nanoseconds")
        need(1_000_000 <= self.cycle_ns <= 100_000_000, "cycle_ns", "must be within 1 ms..100 ms (1_000_000..100_000_000 ns)")
        need(is_integer(self.window) and self.window >= 1, "window", "must be an integer >= 1")
        need(is_integer(self.perfect_hold_cycles) and self.perfect_hold_cycles >= 1, "perfect_hold_cycles", "must be an integer >= 1")
        need(is_integer(self.max_bridged_misses) and self.max_bridged_misses >= 0, "max_bridged_misses", "must be an integer >= 0")
        for name in ("perfect_max_latency_cycles", "perfect_max_jitter_cycles"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and math.isfinite(v) and v > 0, name, "must be a positive number of cycles")
        for name in ("ok_max_miss_rate", "bad_max_miss_rate"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and 0.0 <= v <= 1.0, name, "must be a fraction in [0, 1]")
        need(self.ok_max_miss_rate <= self.bad_max_miss_rate, "ok_max_miss_rate",
             f"must not exceed bad_max_miss_rate ({self.bad_max_miss_rate})")
        try:
            object.__setattr__(self, "initial_control_mode", ControlMode(self.initial_control_mode))
        except ValueError:
            need(False, "initial_control_mode", "must be a ControlMode")


@dataclass(slots=True, frozen=True, eq=False)
class CycleOutcome:
    """What the KRC applies in the cycle just closed."""

    seq: int  # the cycle (measurement seq) that was closed
    answered: bool  # an in-time, well-formed answer arrived
    command: CommandPacket | None  # what the controller applies; None with hold
    bridged: bool  # command is the previous one, repeated over a missing answer
    hold: bool  # no usable command: the arm holds its pose
    state: FriState  # state after this cycle's transitions
    quality: FriQuality
    consecutive_misses: int


class ClosedCycle(NamedTuple):
    """How a cycle closed, for a caller that takes the command applied from the link's slot
    (``FriLink.close``): ``CycleOutcome`` without the packet."""

    seq: int
    answered: bool
    bridged: bool
    hold: bool
    state: FriState
    quality: FriQuality
    consecutive_misses: int


@dataclass(frozen=True)
class FriStatistics:
    """Counters since the last ``start()`` and figures over the window."""

    sent: int  # measurements sent (the open cycle included)
    answered: int  # cycles closed with an in-time answer
    missed: int  # cycles closed without one
    late: int  # well-formed answers that came after their deadline or for an older cycle
    corrupt: int  # packets rejected as malformed / for a seq never sent / before their measurement
    duplicate: int  # extra in-time answers to an already answered cycle
    mode_mismatch: int  # CMD cycles whose command asked for another control mode
    bridged: int  # CMD cycles that repeated the last command
    held: int  # CMD cycles that held the pose
    longest_miss_run: int
    consecutive_misses: int
    window_packets: int  # closed cycles in the window (< window at start-up)
    answer_rate: float
    miss_rate: float
    latency_s: float
    jitter_s: float
    state: FriState
    quality: FriQuality


class FriLink(HoldsAddresses):
    """The KRC's end of one FRI 1.0 connection.  See the module docstring.  Its books (state,
    counters, window) and the commands it holds (as numbers, in slots) are arrays kept by
    ``robot_sim.krc.link_books``'s kernels; a command given as a packet is kept beside its
    numbers, one given as numbers (``receive_fields``) becomes a packet only when asked for."""

    def __init__(self, config: FriConfig | None = None, faults: LinkFaults | None = None):
        self.config = cfg = config if config is not None else FriConfig()
        self.faults = faults
        w = cfg.window
        self._books = books = np.zeros(len(lb.BOOKS), dtype=np.int64)
        books[lb.CYCLE_NS], books[lb.WINDOW] = cfg.cycle_ns, w
        books[lb.PERFECT_HOLD], books[lb.MAX_BRIDGED] = cfg.perfect_hold_cycles, cfg.max_bridged_misses
        books[lb.SMALL_LATENCY] = lb.small_latency(w)
        books[lb.SEQ] = 0  # last seq sent; kept across sessions (see module docstring)
        books[lb.CONTROL_MODE] = int(cfg.initial_control_mode)
        books[lb.STATE] = FriState.OFF
        self._thresholds = np.array([cfg.perfect_max_latency_cycles, cfg.perfect_max_jitter_cycles,
                                     cfg.ok_max_miss_rate, cfg.bad_max_miss_rate], dtype=np.float64)
        self._ring = lb.new_ring(w)
        # the commands it holds, in arrays (link_books' slots); the packets it was given beside them
        self._commands = np.zeros((3, lb.SLOT_ROWS, lb.SLOT_COLUMNS))
        self._meta = np.zeros((3, lb.META), dtype=np.int64)
        self._checks = CommandChecks(self._commands[lb.ARRIVING], self._meta[lb.ARRIVING, :8])
        self._commands_at, self._meta_at = address(self._commands), int64_address(self._meta)
        self._figures = np.zeros(4)
        self._books_at, self._ring_at, self._n_ring = int64_address(books), int64_address(self._ring), len(self._ring)
        self._thresholds_at, self._figures_at = address(self._thresholds), address(self._figures)
        self._reset_session(0)

    # ----------------------------------------------------------------- session
    def _reset_session(self, t_ns: int) -> None:
        b = self._books
        b[lb.FIRST_SEQ] = b[lb.SEQ] + 1
        b[lb.QUALITY] = FriQuality.UNACCEPTABLE
        b[lb.CMD_REQUESTED] = b[lb.PERFECT_RUN] = 0
        b[lb.REFLECTED_SEQ] = -1
        # the open cycle
        b[lb.OPEN], b[lb.DEADLINE], b[lb.HAS_ANSWER], b[lb.ANSWER_LATENCY] = 0, t_ns, 0, lb.NO_LATENCY
        b[lb.HAS_LAST_APPLIED] = 0
        b[lb.SENT:lb.LARGE + 1] = 0  # counters since start(), the window's sums
        lb.reset_ring(self._ring, self.config.window)
        self._last_applied: CommandPacket | None = None
        self._cur_cmd: CommandPacket | None = None
        self.last_reject_reason = ""

    def start(self, t_ns: int) -> None:
        """OFF -> MON.  Resets statistics, quality and any command request."""
        if self.state != FriState.OFF:
            raise RuntimeError(f"FriLink.start: link is already {self.state.name}; stop() it first")
        self._reset_session(int(t_ns))
        self._books[lb.STATE] = FriState.MON

    def stop(self) -> None:
        """Any state -> OFF.  An open cycle is abandoned; statistics stay readable."""
        b = self._books
        b[lb.STATE] = FriState.OFF
        b[lb.OPEN] = b[lb.CMD_REQUESTED] = b[lb.HAS_LAST_APPLIED] = 0
        self._cur_cmd = None
        self._last_applied = None

    def request_command_mode(self) -> bool:
        """Ask for CMD; it is entered once quality has been PERFECT long enough.  False in OFF."""
        state = self.state
        if state == FriState.OFF:
            return False
        if state == FriState.MON:
            self._books[lb.CMD_REQUESTED] = 1
        return True

    def request_monitor_mode(self) -> bool:
        """CMD -> MON now (and forget a pending request).  False in OFF."""
        state = self.state
        if state == FriState.OFF:
            return False
        self._books[lb.CMD_REQUESTED] = 0
        if state == FriState.CMD:
            self._leave_cmd()
        return True

    def switch_control_mode(self, mode: ControlMode) -> bool:
        """Change the control mode; FRI allows this only in MON (False otherwise, nothing changes)."""
        mode = ControlMode(mode)  # an unknown mode is a programming error: ValueError
        if self.state != FriState.MON:
            return False
        self._books[lb.CONTROL_MODE] = mode
        return True

    def _leave_cmd(self) -> None:
        b = self._books
        b[lb.STATE] = FriState.MON
        b[lb.CMD_REQUESTED] = b[lb.HAS_LAST_APPLIED] = 0
        self._last_applied = None  # bridging must never reach back into an earlier CMD session

    # --------------------------------------------------------------- read-outs
    @property
    def state(self) -> FriState:
        return _STATES[self._books[lb.STATE]]

    @property
    def quality(self) -> FriQuality:
        return _QUALITIES[self._books[lb.QUALITY]]

    @property
    def control_mode(self) -> ControlMode:
        return _MODES[self._books[lb.CONTROL_MODE]]

    @property
    def seq(self) -> int:
        """Seq of the last measurement sent (0 before the first)."""
        return int(self._books[lb.SEQ])

    @property
    def last_applied(self) -> CommandPacket | None:
        """The command the KRC applied last in this CMD session (None in MON)."""
        if self._last_applied is _IN_SLOT:
            self._last_applied = _slot_packet(self._commands, self._meta, lb.APPLIED)
        return self._last_applied

    @property
    def has_last_applied(self) -> bool:
        return bool(self._books[lb.HAS_LAST_APPLIED])

    @property
    def command_requested(self) -> bool:
        return bool(self._books[lb.CMD_REQUESTED])

    @property
    def consecutive_misses(self) -> int:
        return int(self._books[lb.CONSECUTIVE])

    def statistics(self) -> FriStatistics:
        lb.FIGURES(self._books_at, self._ring_at, self._n_ring, self._figures_at)
        answer_rate, miss_rate, latency_s, jitter_s = self._figures.tolist()
        b = self._books.tolist()
        return FriStatistics(
            sent=b[lb.SENT], answered=b[lb.ANSWERED], missed=b[lb.MISSED], late=b[lb.LATE], corrupt=b[lb.CORRUPT],
            duplicate=b[lb.DUPLICATE], mode_mismatch=b[lb.MODE_MISMATCH], bridged=b[lb.BRIDGED], held=b[lb.HELD],
            longest_miss_run=b[lb.LONGEST_RUN], consecutive_misses=b[lb.CONSECUTIVE], window_packets=b[lb.W_N],
            answer_rate=answer_rate, miss_rate=miss_rate, latency_s=latency_s, jitter_s=jitter_s,
            state=_STATES[b[lb.STATE]], quality=_QUALITIES[b[lb.QUALITY]],
        )

    # ------------------------------------------------------------------- cycle
    def measurement(self, t_ns: int, msr_jnt_pos, msr_cart_pos, est_ext_tcp_ft) -> MeasurementPacket:
        """Open the cycle at ``t_ns`` and return the packet the KRC sends."""
        t_ns = int(t_ns)
        q = np.array(msr_jnt_pos, dtype=np.float64)
        x = np.array(msr_cart_pos, dtype=np.float64)
        ft = np.array(est_ext_tcp_ft, dtype=np.float64)
        seq = self.open_cycle(t_ns, q.shape == (_JNT,) and x.shape == (_CART,) and ft.shape == (_FT,))
        if seq < 0:
            raise ValueError(f"FriLink.measurement: shapes msr_jnt_pos {q.shape}, msr_cart_pos {x.shape}, "
                             f"est_ext_tcp_ft {ft.shape}; expected (7,), (12,), (6,)")
        reflected, state, quality, mode, answer_rate, latency_s, jitter_s, miss_rate = self.sent_header()
        return MeasurementPacket(seq, reflected, t_ns, _STATES[state], _QUALITIES[quality], _MODES[mode], q, x, ft,
                                 answer_rate, latency_s, jitter_s, miss_rate)

    def open_cycle(self, t_ns: int, shapes_ok: bool = True) -> int:
        """``measurement`` without the packet, for a sender that keeps the numbers (``RobotCell.measure``):
        the seq sent (-1: numbers of the wrong shapes); what else the packet says: ``sent_header``."""
        seq = lb.MEASURE(self._books_at, self._ring_at, self._n_ring, t_ns, shapes_ok, self._figures_at)
        if seq == lb.ERR_SHAPES:
            return -1
        if seq < 0:
            raise _not_opened(seq, t_ns, self._books)
        self._cur_cmd = None
        return seq

    def sent_header(self) -> tuple[int, int, int, int, float, float, float, float]:
        """The open cycle's packet but its seq, time and numbers, read before its answer comes:
        reflected seq, state, quality, control mode, answer rate, latency, jitter, miss rate."""
        b = self._books
        answer_rate, miss_rate, latency_s, jitter_s = self._figures.tolist()
        return (int(b[lb.REFLECTED_SEQ]), int(b[lb.STATE]), int(b[lb.QUALITY]), int(b[lb.CONTROL_MODE]), answer_rate,
                latency_s, jitter_s, miss_rate)

    def deliver_measurement(self, m: MeasurementPacket) -> MeasurementPacket | None:
        """``m`` as the remote gets it: None if the fault hook lost it."""
        if self.faults is not None and self.faults.measurement_lost():
            return None
        return m

    def _reject(self, reason: str) -> bool:
        self.last_reject_reason = reason
        return False

    def receive(self, packet: CommandPacket, t_ns: int, *, owned: bool = False) -> bool:
        """A command packet arrives at ``t_ns``.  True if accepted as this cycle's answer.
        ``owned``: the caller made the packet for this call, float64 arrays nobody else
        holds and a ControlMode (what ``CommandPacket.copy`` makes): it is kept as it is."""
        t_ns = int(t_ns)
        b = self._books
        if b[lb.STATE] == lb.OFF:  # an int: a numpy integer against an IntEnum takes microseconds
            return self._reject("link is OFF")
        try:
            problem = command_problem(packet, self._checks)  # its numbers left in the ARRIVING slot
        except Exception as exc:
            problem = f"unreadable packet ({type(exc).__name__}: {exc})"
        if problem is not None:
            return self._arrive(problem, -1, 0, t_ns, None)
        # kept if accepted; a copy: the sender may reuse its buffers, the wire would not share them
        return self._arrive(None, int(packet.seq), int(packet.requested_mode), t_ns,
                            packet if owned else packet.copy())

    def receive_fields(self, seq, mode, cart_pos, cart_stiffness, cart_damping, add_tcp_ft, t_ns: int) -> bool:
        """``receive`` of the packet these fields make (a ``robot/command`` message's), without
        making it: the numbers go straight to where they are checked and kept; the packet is
        made only if it is asked for (``last_applied``, a cycle's outcome).  What the fields
        of a CART_IMP command (or of no mode) cannot be goes the packet's way, and fares as
        there."""
        if (type(seq) is not int or type(mode) is not int or not (mode == 2 or mode == 0) or len(cart_pos) != _CART
                or len(cart_stiffness) != _FT or len(cart_damping) != _FT or len(add_tcp_ft) != _FT):
            return self.receive(CommandPacket(seq=seq, cart_pos=np.array(cart_pos, dtype=np.float64),
                                              cart_stiffness=np.array(cart_stiffness, dtype=np.float64),
                                              cart_damping=np.array(cart_damping, dtype=np.float64),
                                              add_tcp_ft=np.array(add_tcp_ft, dtype=np.float64),
                                              requested_mode=control_mode_or_value(mode)), t_ns, owned=True)
        t_ns = int(t_ns)
        b = self._books
        if b[lb.STATE] == lb.OFF:
            return self._reject("link is OFF")
        problem = f"seq is negative ({seq})" if seq < 0 else None
        if problem is None:
            values, present = self._checks.values, self._checks.present
            values[0, :_CART] = cart_pos
            values[1, :_FT] = cart_stiffness
            values[2, :_FT] = cart_damping
            values[3, :_FT] = add_tcp_ft
            present[:] = _CART_IMP_PRESENT
            problem = checked_in_place(self._checks, (cart_pos, cart_stiffness, cart_damping, add_tcp_ft))
        return self._arrive(problem, seq, mode, t_ns, _IN_SLOT)

    def _arrive(self, problem: str | None, s: int, mode: int, t_ns: int, kept) -> bool:
        """An answer echoing ``s`` whose checks found ``problem`` (its numbers in the ARRIVING
        slot when they found none) meets the books; ``kept``: what ``_cur_cmd`` holds if it is
        accepted.  True if it is this cycle's answer."""
        b = self._books
        if problem is None and s > _INT64_MAX:  # past any seq the books can hold
            problem = _rejection(lb.NEVER_SENT, s, t_ns, b, self._ring, self.config.window)
        if problem is not None:
            b[lb.CORRUPT] += 1
            return self._reject(problem)
        fate = lb.RECEIVE(self._books_at, self._ring_at, self._n_ring, self._commands_at, self._meta_at, s, mode, t_ns)
        if fate == lb.ACCEPTED:
            self._cur_cmd = kept
            self.last_reject_reason = ""
            return True
        return self._reject(_rejection(fate, s, t_ns, b, self._ring, self.config.window))

    def deliver(self, packet: CommandPacket, t_sent_ns: int, *, owned: bool = False) -> bool:
        """Send ``packet`` from the remote at ``t_sent_ns`` through the fault hook, then
        ``receive`` it (``owned`` as there; through the faults, each arrival is copied)."""
        if self.faults is None:
            return self.receive(packet, t_sent_ns, owned=owned)
        accepted = False
        # each arrival is judged by its arrival time against the cycle it reaches: a copy
        # within the deadline is a duplicate, a packet held back past it is late
        for arrived, t_ns in self.faults.transmit(packet, t_sent_ns):
            accepted = self.receive(arrived, t_ns) or accepted
        return accepted

    def end_cycle(self, t_ns: int) -> CycleOutcome:
        """Close the open cycle at its deadline and decide what the KRC applies."""
        closed = self.close(t_ns)
        if closed.hold:
            command = None
        else:
            command = self._cur_cmd if not closed.bridged else self.last_applied
            if command is _IN_SLOT:  # the cycle's answer, come as numbers: the APPLIED slot holds it now
                command = self._last_applied = self._cur_cmd = _slot_packet(self._commands, self._meta, lb.APPLIED)
        return CycleOutcome(closed.seq, closed.answered, command, closed.bridged, closed.hold, closed.state,
                            closed.quality, closed.consecutive_misses)

    def close(self, t_ns: int) -> ClosedCycle:
        """``end_cycle`` for a caller that takes the command applied from the APPLIED slot
        (``applied_numbers_at``; robot_sim.cell's compiled close): no packet is made."""
        t_ns = int(t_ns)
        code = lb.END_CYCLE(self._books_at, self._ring_at, self._n_ring, self._thresholds_at, self._commands_at,
                            self._meta_at, t_ns)
        if code < 0:
            if code == lb.ERR_NOT_OPEN:
                raise RuntimeError("FriLink.end_cycle: no open cycle; call measurement() first")
            raise ValueError(f"FriLink.end_cycle: t_ns = {t_ns} is before the cycle's deadline "
                             f"{self._books[lb.DEADLINE]}")
        applied = code & 3
        if applied == lb.APPLY_ANSWER:
            self._last_applied = self._cur_cmd
        elif not code & lb.HAS_LAST:
            self._last_applied = None
        b = self._books.tolist()
        return ClosedCycle(b[lb.SEQ], self._cur_cmd is not None, applied == lb.APPLY_LAST, applied == lb.APPLY_NONE,
                           _STATES[b[lb.STATE]], _QUALITIES[b[lb.QUALITY]], b[lb.CONSECUTIVE])

    @property
    def applied_numbers_at(self) -> int:
        """Where the command applied last is, as numbers: (8, 12) float64, C-contiguous, a row a
        vector of its packet (robot_sim.krc.packets' order: cart_pos, cart_stiffness, ...)."""
        return self._commands_at + lb.APPLIED * lb.SLOT_ROWS * lb.SLOT_COLUMNS * 8


def _not_opened(code: int, t_ns: int, b: np.ndarray) -> Exception:
    """Why ``link_books.MEASURE`` opened no cycle at ``t_ns`` (``code``), as the error to raise."""
    if code == lb.ERR_OFF:
        return RuntimeError("FriLink.measurement: link is OFF; call start() first")
    if code == lb.ERR_OPEN:
        return RuntimeError(f"FriLink.measurement: cycle seq {b[lb.SEQ]} is still open; call end_cycle() first")
    return ValueError(f"FriLink.measurement: t_ns = {t_ns} is before the previous cycle's deadline {b[lb.DEADLINE]}")


def _rejection(fate: int, s: int, t_ns: int, b: np.ndarray, ring: np.ndarray, w: int) -> str:
    """Why the answer echoing ``s``, arrived at ``t_ns``, was not this cycle's (``fate``)."""
    if fate == lb.NEVER_SENT:
        return f"seq {s} was never sent (last sent {b[lb.SEQ]})"
    if fate == lb.EARLIER_SESSION:
        return f"seq {s} belongs to an earlier session"
    if fate == lb.BEFORE_SENT:
        return f"arrived at {t_ns}, before measurement {s} was sent at {ring[4 * w + 1 + s % (w + 1)]}"
    if fate == lb.DUPLICATE_ANSWER:
        return f"duplicate answer to seq {s}"
    if fate == lb.AFTER_DEADLINE:
        return f"answer to seq {s} arrived at {t_ns}, deadline {b[lb.DEADLINE]}"
    return f"answer to seq {s} arrived after its cycle closed (current seq {b[lb.SEQ]})"


def _slot_packet(commands: np.ndarray, meta: np.ndarray, slot: int) -> CommandPacket:
    """The command in the link's ``slot`` as a packet (float64 arrays of its own)."""
    values, flags = commands[slot], meta[slot].tolist()

    def joints(row):
        return values[row, :_JNT].copy() if flags[row] else None

    return CommandPacket(seq=flags[lb.CMD_SEQ], cart_pos=values[0, :_CART].copy(),
                         cart_stiffness=values[1, :_FT].copy(), cart_damping=values[2, :_FT].copy(),
                         add_tcp_ft=values[3, :_FT].copy(), jnt_pos=joints(4), requested_mode=_MODES[flags[lb.MODE]],
                         jnt_stiffness=joints(5), jnt_damping=joints(6), add_jnt_trq=joints(7))


# the enums by value (their values are 0, 1, ...): faster than calling the enum
_STATES, _QUALITIES, _MODES = tuple(FriState), tuple(FriQuality), tuple(ControlMode)
# a command the link holds only in its slot (it came as a message's numbers): its packet is made when asked for
_IN_SLOT = object()
# receive_fields: which of the eight vectors a CART_IMP command carries
_CART_IMP_PRESENT = np.array([1, 1, 1, 1, 0, 0, 0, 0], dtype=np.int64)
_INT64_MAX = 2**63 - 1
