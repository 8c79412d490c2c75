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

import numpy as np

from robot_sim.cycle import FRI_CYCLE_NS
from robot_sim.krc.faults import LinkFaults
from robot_sim.krc.packets import (_CART, _FT, _JNT, CommandPacket, ControlMode, FriQuality, FriState,
                                   MeasurementPacket, command_problem, is_integer)

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


_NO_LATENCY = -1


class CycleWindow:
    """The last ``size`` closed cycles of a session: which were missed and each answer's
    latency, with the running sums the link's figures and quality are taken from.

    A ring indexed by seq % size (seqs are consecutive within a session, so pushing seq
    s evicts s - size).  Plain lists: scalar access to Python lists is several times
    faster than to numpy arrays.  Latencies are integer ns, so the sums are exact, with
    no drift over long runs.
    """

    __slots__ = ("size", "seqs", "missed", "latencies", "n", "misses", "lat_n", "lat_sum", "lat_sq")

    def __init__(self, size: int):
        self.size = size
        self.seqs = [-1] * size
        self.missed = [False] * size
        self.latencies = [_NO_LATENCY] * size
        self.n = 0  # closed cycles in the window
        self.misses = 0
        self.lat_n = 0
        self.lat_sum = 0
        self.lat_sq = 0

    def push(self, seq: int, missed: bool, latency: int) -> None:
        """Cycle ``seq`` closed (evicting seq - size)."""
        i = seq % self.size
        if self.seqs[i] >= 0:
            if self.missed[i]:
                self.misses -= 1
            old = self.latencies[i]
            if old != _NO_LATENCY:
                self.lat_n -= 1
                self.lat_sum -= old
                self.lat_sq -= old * old
        else:
            self.n += 1
        self.seqs[i] = seq
        self.missed[i] = missed
        self.latencies[i] = latency
        if latency != _NO_LATENCY:
            self.lat_n += 1
            self.lat_sum += latency
            self.lat_sq += latency * latency
        if missed:
            self.misses += 1

    def late_latency(self, seq: int, latency: int) -> None:
        """A late answer's latency still belongs in the window while its cycle is there."""
        i = seq % self.size
        if latency != _NO_LATENCY and self.seqs[i] == seq and self.latencies[i] == _NO_LATENCY:
            self.latencies[i] = latency
            self.lat_n += 1
            self.lat_sum += latency
            self.lat_sq += latency * latency

    def figures(self) -> tuple[float, float, float, float]:
        """(answer_rate, miss_rate, latency_s, jitter_s) over the window."""
        n = self.n
        if n == 0:
            return 0.0, 0.0, 0.0, 0.0
        miss_rate = self.misses / n
        ln = self.lat_n
        if ln == 0:
            return 1.0 - miss_rate, miss_rate, 0.0, 0.0
        # n*sum(x^2) - sum(x)^2 is exact in integers, so the variance is never negative.
        var_num = ln * self.lat_sq - self.lat_sum * self.lat_sum
        return (1.0 - miss_rate, miss_rate, self.lat_sum / ln * 1e-9, math.sqrt(var_num) / ln * 1e-9)

    def quality(self, cfg: FriConfig) -> FriQuality:
        """The link's quality from the window (the module docstring's table)."""
        n = self.n
        if n == 0:
            return FriQuality.UNACCEPTABLE
        misses = self.misses
        if misses == 0:
            ln = self.lat_n  # == n: every cycle in the window was answered in time
            cycle = cfg.cycle_ns
            mean_ok = self.lat_sum < cfg.perfect_max_latency_cycles * cycle * ln
            var = (ln * self.lat_sq - self.lat_sum * self.lat_sum) / (ln * ln)
            jitter_ok = var < (cfg.perfect_max_jitter_cycles * cycle) ** 2
            if mean_ok and jitter_ok:
                return FriQuality.PERFECT
            return FriQuality.OK
        # A small slack so that "at most 2 %" holds for exactly 2 of 100.
        if misses <= cfg.ok_max_miss_rate * n + 1e-9:
            return FriQuality.OK
        if misses <= cfg.bad_max_miss_rate * n + 1e-9:
            return FriQuality.BAD
        return FriQuality.UNACCEPTABLE


class FriLink:
    """The KRC's end of one FRI 1.0 connection.  See the module docstring."""

    def __init__(self, config: FriConfig | None = None, faults: LinkFaults | None = None):
        self.config = config if config is not None else FriConfig()
        self.faults = faults
        self._seq = 0  # last seq sent; kept across sessions (see module docstring)
        self._control_mode = self.config.initial_control_mode
        self._state = FriState.OFF
        self._reset_session(0)

    # ----------------------------------------------------------------- session
    def _reset_session(self, t_ns: int) -> None:
        w = self.config.window
        self._started_ns = t_ns
        self._first_seq = self._seq + 1
        self._quality = FriQuality.UNACCEPTABLE
        self._cmd_requested = False
        self._perfect_run = 0
        self._last_applied: CommandPacket | None = None
        self._reflected_seq = -1
        # The open cycle.
        self._open = False
        self._deadline_ns = t_ns
        self._cur_cmd: CommandPacket | None = None
        self._cur_lat = _NO_LATENCY
        self._window = CycleWindow(w)
        # Send times of the open cycle and the window's cycles, for late answers' latency.
        self._send_seq = [-1] * (w + 1)
        self._send_ns = [0] * (w + 1)
        # Counters since start().
        self._sent = self._answered = self._missed = self._late = self._corrupt = 0
        self._duplicate = self._mode_mismatch = self._bridged = self._held = 0
        self._consecutive = self._longest_run = 0
        self.last_reject_reason = ""

    def start(self, t_ns: int) -> None:
        """OFF -> MON.  Resets statistics, quality and any command request."""
        if self._state != FriState.OFF:
            raise RuntimeError(f"FriLink.start: link is already {self._state.name}; stop() it first")
        self._reset_session(int(t_ns))
        self._state = FriState.MON

    def stop(self) -> None:
        """Any state -> OFF.  An open cycle is abandoned; statistics stay readable."""
        self._state = FriState.OFF
        self._open = False
        self._cur_cmd = None
        self._cmd_requested = False
        self._last_applied = None

    def request_command_mode(self) -> bool:
        """Ask for CMD; it is entered once quality has been PERFECT long enough.  False in OFF."""
        if self._state == FriState.OFF:
            return False
        if self._state == FriState.MON:
            self._cmd_requested = True
        return True

    def request_monitor_mode(self) -> bool:
        """CMD -> MON now (and forget a pending request).  False in OFF."""
        if self._state == FriState.OFF:
            return False
        self._cmd_requested = False
        if self._state == FriState.CMD:
            self._leave_cmd()
        return True

    def switch_control_mode(self, mode: ControlMode) -> bool:
        """Change the control mode; FRI allows this only in MON (False otherwise, nothing changes)."""
        mode = ControlMode(mode)  # an unknown mode is a programming error: ValueError
        if self._state != FriState.MON:
            return False
        self._control_mode = mode
        return True

    def _leave_cmd(self) -> None:
        self._state = FriState.MON
        self._cmd_requested = False
        self._last_applied = None  # bridging must never reach back into an earlier CMD session

    # --------------------------------------------------------------- read-outs
    @property
    def state(self) -> FriState:
        return self._state

    @property
    def quality(self) -> FriQuality:
        return self._quality

    @property
    def control_mode(self) -> ControlMode:
        return self._control_mode

    @property
    def seq(self) -> int:
        """Seq of the last measurement sent (0 before the first)."""
        return self._seq

    @property
    def last_applied(self) -> CommandPacket | None:
        """The command the KRC applied last in this CMD session (None in MON)."""
        return self._last_applied

    @property
    def command_requested(self) -> bool:
        return self._cmd_requested

    @property
    def consecutive_misses(self) -> int:
        return self._consecutive

    def statistics(self) -> FriStatistics:
        answer_rate, miss_rate, latency_s, jitter_s = self._window.figures()
        return FriStatistics(
            sent=self._sent, answered=self._answered, missed=self._missed, late=self._late,
            corrupt=self._corrupt, duplicate=self._duplicate, mode_mismatch=self._mode_mismatch,
            bridged=self._bridged, held=self._held, longest_miss_run=self._longest_run,
            consecutive_misses=self._consecutive, window_packets=self._window.n,
            answer_rate=answer_rate, miss_rate=miss_rate, latency_s=latency_s, jitter_s=jitter_s,
            state=self._state, quality=self._quality,
        )

    # ------------------------------------------------------------------- cycle
    def measurement(self, t_ns: int, msr_jnt_pos, msr_cart_pos, est_ext_tcp_ft) -> MeasurementPacket:
        """Open the cycle at ``t_ns`` and return the packet the KRC sends."""
        t_ns = int(t_ns)
        if self._state == FriState.OFF:
            raise RuntimeError("FriLink.measurement: link is OFF; call start() first")
        if self._open:
            raise RuntimeError(f"FriLink.measurement: cycle seq {self._seq} is still open; call end_cycle() first")
        if self._seq >= self._first_seq and t_ns < self._deadline_ns:
            raise ValueError(f"FriLink.measurement: t_ns = {t_ns} is before the previous cycle's deadline {self._deadline_ns}")
        q = np.array(msr_jnt_pos, dtype=np.float64)
        x = np.array(msr_cart_pos, dtype=np.float64)
        ft = np.array(est_ext_tcp_ft, dtype=np.float64)
        if q.shape != (_JNT,) or x.shape != (_CART,) or ft.shape != (_FT,):
            raise ValueError(
                f"FriLink.measurement: shapes msr_jnt_pos {q.shape}, msr_cart_pos {x.shape}, "
                f"est_ext_tcp_ft {ft.shape}; expected (7,), (12,), (6,)")

        self._seq += 1
        seq = self._seq
        j = seq % (self.config.window + 1)
        self._send_seq[j] = seq
        self._send_ns[j] = t_ns
        self._open = True
        self._deadline_ns = t_ns + self.config.cycle_ns
        self._cur_cmd = None
        self._cur_lat = _NO_LATENCY
        self._sent += 1

        answer_rate, miss_rate, latency_s, jitter_s = self._window.figures()
        return MeasurementPacket(
            seq, self._reflected_seq, t_ns, self._state, self._quality, self._control_mode,
            q, x, ft, answer_rate, latency_s, jitter_s, miss_rate,
        )

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
        if self._state == FriState.OFF:
            return self._reject("link is OFF")
        try:
            problem = command_problem(packet)
        except Exception as exc:
            problem = f"unreadable packet ({type(exc).__name__}: {exc})"
        if problem is not None:
            self._corrupt += 1
            return self._reject(problem)
        s = int(packet.seq)
        if s > self._seq:
            self._corrupt += 1
            return self._reject(f"seq {s} was never sent (last sent {self._seq})")
        if s < self._first_seq:
            self._late += 1
            return self._reject(f"seq {s} belongs to an earlier session")

        j = s % (self.config.window + 1)
        known_send = self._send_seq[j] == s
        if known_send and t_ns < self._send_ns[j]:
            self._corrupt += 1
            return self._reject(f"arrived at {t_ns}, before measurement {s} was sent at {self._send_ns[j]}")
        self._reflected_seq = s
        latency = t_ns - self._send_ns[j] if known_send else _NO_LATENCY

        if s == self._seq and self._open:
            if t_ns < self._deadline_ns:
                if self._cur_cmd is not None:
                    self._duplicate += 1
                    return self._reject(f"duplicate answer to seq {s}")
                # A copy: the sender may reuse its buffers, the wire would not share them.
                self._cur_cmd = packet if owned else packet.copy()
                self._cur_lat = latency
                self.last_reject_reason = ""
                return True
            self._late += 1
            if self._cur_lat == _NO_LATENCY:
                self._cur_lat = latency
            return self._reject(f"answer to seq {s} arrived at {t_ns}, deadline {self._deadline_ns}")

        self._late += 1
        self._window.late_latency(s, latency)
        return self._reject(f"answer to seq {s} arrived after its cycle closed (current seq {self._seq})")

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
        t_ns = int(t_ns)
        if not self._open:
            raise RuntimeError("FriLink.end_cycle: no open cycle; call measurement() first")
        if t_ns < self._deadline_ns:
            raise ValueError(f"FriLink.end_cycle: t_ns = {t_ns} is before the cycle's deadline {self._deadline_ns}")
        self._open = False
        seq = self._seq
        cmd = self._cur_cmd
        answered = cmd is not None

        self._window.push(seq, not answered, self._cur_lat)
        if answered:
            self._answered += 1
            self._consecutive = 0
        else:
            self._missed += 1
            self._consecutive += 1
            if self._consecutive > self._longest_run:
                self._longest_run = self._consecutive

        quality = self._quality = self._window.quality(self.config)
        self._perfect_run = self._perfect_run + 1 if quality == FriQuality.PERFECT else 0

        if self._state == FriState.CMD and quality < FriQuality.OK:
            self._leave_cmd()
        elif (self._state == FriState.MON and self._cmd_requested
              and self._perfect_run >= self.config.perfect_hold_cycles):
            self._state = FriState.CMD
            self._cmd_requested = False
            self._last_applied = None

        bridged = False
        applied = None
        if self._state == FriState.CMD:
            if answered:
                if cmd.requested_mode == self._control_mode:
                    applied = self._last_applied = cmd
                else:
                    self._mode_mismatch += 1
            elif self._consecutive <= self.config.max_bridged_misses and self._last_applied is not None:
                applied = self._last_applied
                bridged = True
                self._bridged += 1
            if applied is None:
                self._held += 1
        return CycleOutcome(seq, answered, applied, bridged, applied is None, self._state, quality, self._consecutive)
