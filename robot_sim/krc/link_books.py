"""The KRC's books on the FRI exchange (``robot_sim.krc.link``), kept in arrays and kept by
numba kernels, so that a compiled loop can keep them too.

``FriLink`` is the interface and says what the books mean; this module holds them.  One
int64 array (``BOOKS``, indexed by the names below) holds the link's state, counters,
the window's running sums and its settings; a second (``new_ring``) the window's cycles and
the send times a late answer's latency is taken from; a float64 array the quality
thresholds; and the commands the link holds, as numbers in three slots (below).  The
kernels take their addresses (``kernel_plumbing.addresses``): a measurement opens a cycle,
an answer arrives (its numbers checked in place, then kept), a cycle closes (the answer
applied, or the last one again, kept as the applied command).

The window's figures and quality are computed exactly, as integers: the running sums of
the latencies (integer ns) never drift.  The kernels keep the sums in int64 for the
latencies that are *small* for the window (``small_latency``: ``window**2 * latency**2 <
2**53``, so every product and quotient of the formulas is exact in float64 too: 0.95 ms
for a window of 100); while a larger one is in the window, the figures are computed from
the ring in Python integers (``window_figures`` and ``window_quality`` are plain Python,
compiled for the small case and run by Python for the large one: one formula).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, objmode

from kernel_plumbing.addresses import JIT, addresses, carray_at, entry, int64_array_at

NO_LATENCY = -1
OFF, MON, CMD = 0, 1, 2  # FriState
UNACCEPTABLE, BAD, OK, PERFECT = 0, 1, 2, 3  # FriQuality

BOOKS = ("seq", "first_seq", "state", "quality", "control_mode", "cmd_requested", "perfect_run", "reflected_seq",
         "open", "deadline_ns", "has_answer", "answer_latency", "has_last_applied",
         "sent", "answered", "missed", "late", "corrupt", "duplicate", "mode_mismatch", "bridged", "held",
         "consecutive", "longest_run",
         "window_n", "window_misses", "latency_n", "latency_sum", "latency_sq", "large_latencies",
         # settings (FriConfig)
         "cycle_ns", "window", "perfect_hold_cycles", "max_bridged_misses", "small_latency")
(SEQ, FIRST_SEQ, STATE, QUALITY, CONTROL_MODE, CMD_REQUESTED, PERFECT_RUN, REFLECTED_SEQ, OPEN, DEADLINE,
 HAS_ANSWER, ANSWER_LATENCY, HAS_LAST_APPLIED, SENT, ANSWERED, MISSED, LATE, CORRUPT, DUPLICATE, MODE_MISMATCH,
 BRIDGED, HELD, CONSECUTIVE, LONGEST_RUN, W_N, W_MISSES, LAT_N, LAT_SUM, LAT_SQ, LARGE, CYCLE_NS, WINDOW,
 PERFECT_HOLD, MAX_BRIDGED, SMALL_LATENCY) = range(len(BOOKS))
# the thresholds (float64): perfect_max_latency_cycles, perfect_max_jitter_cycles, ok_max_miss_rate, bad_max_miss_rate
_PML, _PMJ, _OKR, _BADR = range(4)

# The commands the link holds, in slots: an answer as it arrives (where its numbers are
# checked: robot_sim.krc.packets' check buffers), the cycle's accepted answer, the last
# command applied in this CMD session.  A slot's numbers are float64 (8, 12), a row a
# vector of a command packet (packets._VECTORS' order), its meta int64 (10): the eight
# vectors' presence, the requested mode, the seq.
ARRIVING, ANSWER, APPLIED = range(3)
SLOT_ROWS, SLOT_COLUMNS, META = 8, 12, 10
MODE, CMD_SEQ = 8, 9  # meta's columns after the presence flags

# what a measurement's call says when it cannot open a cycle
ERR_OFF, ERR_OPEN, ERR_BEFORE_DEADLINE, ERR_SHAPES = -1, -2, -3, -4
# what becomes of an answer (receive)
ACCEPTED, NEVER_SENT, EARLIER_SESSION, BEFORE_SENT, DUPLICATE_ANSWER, AFTER_DEADLINE, AFTER_CLOSE = range(7)
# what a cycle's close applies: nothing (hold), the cycle's answer, the last one again (bridged);
# plus HAS_LAST when a command applied in this CMD session is kept; negative: it cannot close
APPLY_NONE, APPLY_ANSWER, APPLY_LAST, HAS_LAST = 0, 1, 2, 4
ERR_NOT_OPEN, ERR_EARLY = -1, -2


def small_latency(window: int) -> int:
    """The latencies (ns) below which the window's sums stay exact in int64 and float64:
    ``window**2 * latency**2 < 2**53``."""
    return math.isqrt((2**53 - 1) // (window * window))


def window_figures(n, misses, latency_n, latency_sum, latency_sq):
    """(answer_rate, miss_rate, latency_s, jitter_s) over the window."""
    if n == 0:
        return 0.0, 0.0, 0.0, 0.0
    miss_rate = misses / n
    if latency_n == 0:
        return 1.0 - miss_rate, miss_rate, 0.0, 0.0
    # n*sum(x^2) - sum(x)^2 is exact in integers, so the variance is never negative
    var_num = latency_n * latency_sq - latency_sum * latency_sum
    return 1.0 - miss_rate, miss_rate, latency_sum / latency_n * 1e-9, math.sqrt(var_num) / latency_n * 1e-9


def window_quality(n, misses, latency_n, latency_sum, latency_sq, cycle_ns, perfect_max_latency_cycles,
                   perfect_max_jitter_cycles, ok_max_miss_rate, bad_max_miss_rate):
    """The link's quality from the window (robot_sim.krc.link's table)."""
    if n == 0:
        return UNACCEPTABLE
    if misses == 0:
        # every cycle in the window answered in time: latency_n == n
        mean_ok = latency_sum < perfect_max_latency_cycles * cycle_ns * latency_n
        var = (latency_n * latency_sq - latency_sum * latency_sum) / (latency_n * latency_n)
        jitter_ok = var < (perfect_max_jitter_cycles * cycle_ns) ** 2
        if mean_ok and jitter_ok:
            return PERFECT
        return OK
    # a small slack so that "at most 2 %" holds for exactly 2 of 100
    if misses <= ok_max_miss_rate * n + 1e-9:
        return OK
    if misses <= bad_max_miss_rate * n + 1e-9:
        return BAD
    return UNACCEPTABLE


_figures_small = njit(**JIT)(window_figures)
_quality_small = njit(**JIT)(window_quality)


def _exact_sums(ring: np.ndarray, window: int) -> tuple[int, int]:
    """The window's latency sum and sum of squares in Python integers, from the ring."""
    seqs, latencies = ring[:window].tolist(), ring[2 * window:3 * window].tolist()
    total = squares = 0
    for s, latency in zip(seqs, latencies):
        if s >= 0 and latency != NO_LATENCY:
            total += latency
            squares += latency * latency
    return total, squares


def _figures_exact(books: np.ndarray, ring: np.ndarray) -> tuple[float, float, float, float]:
    total, squares = _exact_sums(ring, int(books[WINDOW]))
    return window_figures(int(books[W_N]), int(books[W_MISSES]), int(books[LAT_N]), total, squares)


def _quality_exact(books: np.ndarray, ring: np.ndarray, thresholds: np.ndarray) -> int:
    total, squares = _exact_sums(ring, int(books[WINDOW]))
    t = thresholds.tolist()
    return window_quality(int(books[W_N]), int(books[W_MISSES]), int(books[LAT_N]), total, squares,
                          int(books[CYCLE_NS]), t[_PML], t[_PMJ], t[_OKR], t[_BADR])


# the kernels below may call Python (objmode) for a window with a large latency: they hold the GIL
_KEEPS_GIL = dict(JIT, nogil=False)


@njit(**_KEEPS_GIL)
def figures_into(b, ring, out):
    """The window's (answer_rate, miss_rate, latency_s, jitter_s) into ``out`` (4)."""
    if b[LARGE] == 0:
        out[0], out[1], out[2], out[3] = _figures_small(b[W_N], b[W_MISSES], b[LAT_N], b[LAT_SUM], b[LAT_SQ])
    else:
        with objmode(a="float64", m="float64", lat="float64", jit="float64"):
            a, m, lat, jit = _figures_exact(b, ring)
        out[0], out[1], out[2], out[3] = a, m, lat, jit


@njit(**_KEEPS_GIL)
def quality_of(b, ring, thresholds):
    if b[LARGE] == 0:
        return _quality_small(b[W_N], b[W_MISSES], b[LAT_N], b[LAT_SUM], b[LAT_SQ], b[CYCLE_NS],
                              thresholds[_PML], thresholds[_PMJ], thresholds[_OKR], thresholds[_BADR])
    with objmode(q="int64"):
        q = _quality_exact(b, ring, thresholds)
    return q


@njit(**JIT, inline="always")
def _add_latency(b, latency, sign):
    if latency > b[SMALL_LATENCY]:
        b[LARGE] += sign
    else:
        b[LAT_SUM] += sign * latency
        b[LAT_SQ] += sign * latency * latency
    b[LAT_N] += sign


@njit(**JIT)
def window_push(b, ring, seq, missed, latency):
    """Cycle ``seq`` closed (evicting seq - window)."""
    w = b[WINDOW]
    i = seq % w
    if ring[i] >= 0:
        if ring[w + i]:
            b[W_MISSES] -= 1
        old = ring[2 * w + i]
        if old != NO_LATENCY:
            _add_latency(b, old, -1)
    else:
        b[W_N] += 1
    ring[i] = seq
    ring[w + i] = missed
    ring[2 * w + i] = latency
    if latency != NO_LATENCY:
        _add_latency(b, latency, 1)
    if missed:
        b[W_MISSES] += 1


@njit(**JIT)
def measure(b, ring, t_ns, shapes_ok, figures):
    """Open a cycle at ``t_ns``: its seq, the window's figures in ``figures``; or ERR_*."""
    if b[STATE] == OFF:
        return ERR_OFF
    if b[OPEN]:
        return ERR_OPEN
    if b[SEQ] >= b[FIRST_SEQ] and t_ns < b[DEADLINE]:
        return ERR_BEFORE_DEADLINE
    if not shapes_ok:
        return ERR_SHAPES
    b[SEQ] += 1
    seq = b[SEQ]
    w = b[WINDOW]
    j = seq % (w + 1)
    ring[3 * w + j] = seq
    ring[4 * w + 1 + j] = t_ns
    b[OPEN] = 1
    b[DEADLINE] = t_ns + b[CYCLE_NS]
    b[HAS_ANSWER] = 0
    b[ANSWER_LATENCY] = NO_LATENCY
    b[SENT] += 1
    figures_into(b, ring, figures)
    return seq


@njit(**JIT, inline="always")
def _copy_slot(commands, meta, src, dst):
    for r in range(SLOT_ROWS):
        for c in range(SLOT_COLUMNS):
            commands[dst, r, c] = commands[src, r, c]
    for c in range(META):
        meta[dst, c] = meta[src, c]


@njit(**JIT)
def receive(b, ring, commands, meta, s, mode, t_ns):
    """A well-formed answer echoing ``s`` (its numbers checked in the ARRIVING slot), asking
    for ``mode``, arrives at ``t_ns`` (the link is not OFF): ACCEPTED (it is the cycle's
    ANSWER now) or why not, counted."""
    if s > b[SEQ]:
        b[CORRUPT] += 1
        return NEVER_SENT
    if s < b[FIRST_SEQ]:
        b[LATE] += 1
        return EARLIER_SESSION
    w = b[WINDOW]
    j = s % (w + 1)
    known = ring[3 * w + j] == s
    sent_ns = ring[4 * w + 1 + j]
    if known and t_ns < sent_ns:
        b[CORRUPT] += 1
        return BEFORE_SENT
    b[REFLECTED_SEQ] = s
    latency = t_ns - sent_ns if known else NO_LATENCY
    if s == b[SEQ] and b[OPEN]:
        if t_ns < b[DEADLINE]:
            if b[HAS_ANSWER]:
                b[DUPLICATE] += 1
                return DUPLICATE_ANSWER
            b[HAS_ANSWER] = 1
            b[ANSWER_LATENCY] = latency
            meta[ARRIVING, MODE], meta[ARRIVING, CMD_SEQ] = mode, s
            _copy_slot(commands, meta, ARRIVING, ANSWER)
            return ACCEPTED
        b[LATE] += 1
        if b[ANSWER_LATENCY] == NO_LATENCY:
            b[ANSWER_LATENCY] = latency
        return AFTER_DEADLINE
    b[LATE] += 1
    # a late answer's latency still belongs in the window while its cycle is there
    i = s % w
    if latency != NO_LATENCY and ring[i] == s and ring[2 * w + i] == NO_LATENCY:
        ring[2 * w + i] = latency
        _add_latency(b, latency, 1)
    return AFTER_CLOSE


@njit(**_KEEPS_GIL)
def end_cycle(b, ring, thresholds, commands, meta, t_ns):
    """Close the open cycle at ``t_ns``: APPLY_* (+ HAS_LAST), or ERR_*; the answer applied
    is the APPLIED slot's now."""
    if not b[OPEN]:
        return ERR_NOT_OPEN
    if t_ns < b[DEADLINE]:
        return ERR_EARLY
    b[OPEN] = 0
    answered = b[HAS_ANSWER] != 0
    window_push(b, ring, b[SEQ], not answered, b[ANSWER_LATENCY])
    if answered:
        b[ANSWERED] += 1
        b[CONSECUTIVE] = 0
    else:
        b[MISSED] += 1
        b[CONSECUTIVE] += 1
        if b[CONSECUTIVE] > b[LONGEST_RUN]:
            b[LONGEST_RUN] = b[CONSECUTIVE]
    quality = quality_of(b, ring, thresholds)
    b[QUALITY] = quality
    b[PERFECT_RUN] = b[PERFECT_RUN] + 1 if quality == PERFECT else 0
    if b[STATE] == CMD and quality < OK:
        b[STATE] = MON  # leaving CMD: a new request is needed, and bridging never reaches back
        b[CMD_REQUESTED] = 0
        b[HAS_LAST_APPLIED] = 0
    elif b[STATE] == MON and b[CMD_REQUESTED] and b[PERFECT_RUN] >= b[PERFECT_HOLD]:
        b[STATE] = CMD
        b[CMD_REQUESTED] = 0
        b[HAS_LAST_APPLIED] = 0
    applied = APPLY_NONE
    if b[STATE] == CMD:
        if answered:
            if meta[ANSWER, MODE] == b[CONTROL_MODE]:
                applied = APPLY_ANSWER
                b[HAS_LAST_APPLIED] = 1
                _copy_slot(commands, meta, ANSWER, APPLIED)
            else:
                b[MODE_MISMATCH] += 1
        elif b[CONSECUTIVE] <= b[MAX_BRIDGED] and b[HAS_LAST_APPLIED]:
            applied = APPLY_LAST
            b[BRIDGED] += 1
        if applied == APPLY_NONE:
            b[HELD] += 1
    return applied + (HAS_LAST if b[HAS_LAST_APPLIED] else 0)


@njit(**_KEEPS_GIL)
def _measure_at(books_at, ring_at, n_ring, t_ns, shapes_ok, figures_at):
    return measure(int64_array_at(books_at, len(BOOKS)), int64_array_at(ring_at, n_ring), t_ns, shapes_ok,
                   carray_at(figures_at, (4,)))


@njit(**JIT, inline="always")
def slots_at(commands_at, meta_at):
    """The command slots at these addresses (a view, in a kernel)."""
    return (carray_at(commands_at, (3, SLOT_ROWS, SLOT_COLUMNS)),
            int64_array_at(meta_at, 3 * META).reshape((3, META)))


@njit(**JIT)
def _receive_at(books_at, ring_at, n_ring, commands_at, meta_at, s, mode, t_ns):
    commands, meta = slots_at(commands_at, meta_at)
    return receive(int64_array_at(books_at, len(BOOKS)), int64_array_at(ring_at, n_ring), commands, meta, s, mode,
                   t_ns)


@njit(**_KEEPS_GIL)
def _end_cycle_at(books_at, ring_at, n_ring, thresholds_at, commands_at, meta_at, t_ns):
    commands, meta = slots_at(commands_at, meta_at)
    return end_cycle(int64_array_at(books_at, len(BOOKS)), int64_array_at(ring_at, n_ring),
                     carray_at(thresholds_at, (4,)), commands, meta, t_ns)


@njit(**_KEEPS_GIL)
def _figures_at(books_at, ring_at, n_ring, figures_at):
    figures_into(int64_array_at(books_at, len(BOOKS)), int64_array_at(ring_at, n_ring), carray_at(figures_at, (4,)))


# called as machine code (kernel_plumbing.addresses.entry)
MEASURE = entry(_measure_at, f"{addresses(4)}, boolean, int64")
RECEIVE = entry(_receive_at, addresses(8))
END_CYCLE = entry(_end_cycle_at, addresses(7))
FIGURES = entry(_figures_at, addresses(4))


def new_ring(window: int) -> np.ndarray:
    """The window's cycles (seq, missed, latency; at seq % window) and the send times of the
    open cycle and the window's (seq, ns; at seq % (window + 1)), in one int64 array."""
    ring = np.empty(5 * window + 2, dtype=np.int64)
    reset_ring(ring, window)
    return ring


def reset_ring(ring: np.ndarray, window: int) -> None:
    w = window
    ring[:w] = -1
    ring[w:2 * w] = 0
    ring[2 * w:3 * w] = NO_LATENCY
    ring[3 * w:4 * w + 1] = -1
    ring[4 * w + 1:] = 0
