"""The reproduction policy's step as one compiled kernel, with the Python policy's bits.

``etar.policy.ReproductionPolicy.step`` is a few dozen numpy calls on 3-vectors per
cycle, each a microsecond of Python around nanoseconds of arithmetic: the impedance
commander's largest cost in a reproduction.  ``CompiledPolicy`` runs the same step in
one numba kernel over preallocated buffers, for the policies it can (no phase turns and
no goal rotation: a position state), and gives the same numbers bit for bit: every
product numpy computes through its BLAS (``a @ b`` of two vectors and
``np.linalg.norm``: ddot; a 3x3 matrix times a vector: dgemv) is the same BLAS
function called from the kernel (``kernel_plumbing.blas``), and everything else is the same
element-wise arithmetic in the same order (numba, like numpy, neither reorders nor
fuses floating-point operations unless told to).  Checked against the Python step on
trajectories through every branch in ``tests/etar/test_policy_kernel.py``.

Where numpy's BLAS cannot be called (``kernel_plumbing.blas.AVAILABLE`` False), or a phase turns,
``compiled_policy`` returns the Python policy: the same numbers, more slowly.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from kernel_plumbing import blas
from kernel_plumbing.addresses import JIT, HoldsAddresses, address, carray_at, entry
from etar.policy import CONTACT_FORCE, MIN_SLIDE, PLACE_SPEED, STALL_SPEED, STALL_TIME, ReproductionPolicy
from etar.policy import DT as CYCLE  # a step's default dt (DT below names its slot in the workspace)

NONE = -(1 << 62)  # None where the Python policy holds an int or None (a phase)

# the float workspace: inputs and constants first, then the state, the output and scratch
X, FORCE, DT, TOL, LEAD, GOAL, HOLD_K, HOLD_D = 0, 3, 6, 7, 8, 9, 12, 21
STATE = 30  # reset() zeroes from here on
F_OUT, REF, PREV, V, STALL_FROM, LAST_D, STALLED_FOR = 30, 33, 36, 39, 42, 45, 48
T1, T2, T3, D = 49, 52, 55, 58  # scratch vectors; D the running law's direction
POSE, TOOL_FORCE, TOOL_F_OUT = 61, 73, 76  # tool_step's: the rows of [R | x], its force in and out
N_FLOAT = 80
# per phase (a row each): direction, stiffness, damping, feedforward, speed, place, aim
P_DIR, P_K, P_D, P_FF, P_SPEED, P_PLACE, P_AIM = 0, 3, 12, 21, 24, 25, 28
P_FLOATS = 31
# the int state
HAS_REF, HAS_PREV, HAS_STALL_FROM, HAS_LAST_D, PHASE, HANDED, VISITED, AT_PLACE, GOAL_REACHED, APPLIED, \
    HAS_GOAL, PHASE_IN, HAS_FORCE, TOOL_FRAME = range(14)
N_INT = 16
# per phase: valid (a law, not None), in place, has a place, has an aim, free, successor (NONE: none)
Q_VALID, Q_IN_PLACE, Q_HAS_PLACE, Q_HAS_AIM, Q_FREE, Q_SUCCESSOR = range(6)
P_INTS = 6
MAX_PHASES = 62  # the phases visited are bits of one int64


@njit(**JIT, inline="always")
def _dot(fn, base, i, j):
    """numpy's ``a @ b`` of the 3-vectors at float offsets i and j of the buffer at ``base``."""
    return blas.call_dot(fn, 3, base + 8 * i, 1, base + 8 * j, 1)


@njit(**JIT, inline="always")
def _gemv(fn, a, x, y, lda=3, trans=False):
    """numpy's ``A @ x`` (``A.T @ x`` with ``trans``) for the 3x3 ``A`` whose rows start
    ``lda`` floats apart at ``a`` (3: C-contiguous; 4: the rotation in a (3, 4) pose),
    into ``y`` (addresses)."""
    blas.call_gemv(fn, np.int32(blas.ROW_MAJOR), np.int32(blas.TRANS if trans else blas.NO_TRANS), 3, 3, 1.0, a,
                   lda, x, 1, 0.0, y, 1)


@njit(**JIT)
def _step(dot_fn, gemv_fn, f_at, s_at, pf_at, pi_at, n_phases):
    """``ReproductionPolicy.step``, or with TOOL_FRAME set ``tool_step``."""
    f = carray_at(f_at, (N_FLOAT,))
    tool_frame = carray_at(s_at, (N_INT,)).view(np.int64)[TOOL_FRAME]
    if tool_frame:
        _gemv(gemv_fn, f_at + 8 * POSE, f_at + 8 * TOOL_FORCE, f_at + 8 * FORCE, 4)
        for i in range(3):
            f[X + i] = f[POSE + 4 * i + 3]
    _law(dot_fn, gemv_fn, f_at, s_at, pf_at, pi_at, n_phases)
    if tool_frame:
        _gemv(gemv_fn, f_at + 8 * POSE, f_at + 8 * F_OUT, f_at + 8 * TOOL_F_OUT, 4, True)


@njit(**JIT, inline="always")
def _law(dot_fn, gemv_fn, f_at, s_at, pf_at, pi_at, n_phases):
    """One ``ReproductionPolicy.step``, line for line (see it for the why of each)."""
    f = carray_at(f_at, (N_FLOAT,))
    s = carray_at(s_at, (N_INT,)).view(np.int64)
    pf = carray_at(pf_at, (max(n_phases, 1), P_FLOATS))
    pq = carray_at(pi_at, (max(n_phases, 1), P_INTS)).view(np.int64)
    dt = f[DT]
    lead = f[LEAD]
    phase = s[PHASE_IN]
    _track_velocity(f, s, dt)
    law = phase if phase != NONE and 0 <= phase < n_phases and pq[phase, Q_VALID] else NONE
    if phase != s[PHASE]:
        _enter_phase(f, s, pf, pq, phase, law, lead)
    if s[HANDED] != NONE:
        phase = law = s[HANDED]
    if law != NONE and s[HAS_FORCE] and not s[GOAL_REACHED]:
        law, phase = _unless_blocked(dot_fn, f, f_at, s, pf, pq, law, phase, dt, lead, n_phases)
    s[APPLIED] = NONE if s[GOAL_REACHED] or law == NONE else phase
    if s[GOAL_REACHED] or law == NONE:
        if not s[HAS_REF]:
            for i in range(3):
                f[REF + i] = f[X + i]
            s[HAS_REF] = 1
        _hold_force(gemv_fn, f, f_at)
        return
    for i in range(3):
        f[D + i] = pf[law, P_DIR + i]
    if pq[law, Q_HAS_AIM]:
        _head_for_aim(dot_fn, f, f_at, pf, law, lead)
    if pq[law, Q_FREE] and not pq[law, Q_HAS_AIM] and s[HAS_FORCE]:
        _along_contact(dot_fn, f, f_at)
    for i in range(3):
        f[LAST_D + i] = f[D + i]
    s[HAS_LAST_D] = 1
    in_place = pq[law, Q_IN_PLACE]
    if not in_place:
        _advance_reference(dot_fn, f, f_at, pf, law, dt, lead)
    elif pq[law, Q_HAS_PLACE]:
        _reference_to_place(dot_fn, f, f_at, pf, law, dt, lead)
    going = in_place and pq[law, Q_HAS_PLACE] and not s[AT_PLACE]
    if going:
        there = _at_place(dot_fn, f, f_at, pf, law, lead)
        s[AT_PLACE] = 1 if there else 0
        going = not there
    if going:
        _hold_force(gemv_fn, f, f_at)
    else:
        _spring(gemv_fn, f, f_at, pf_at + 8 * (law * P_FLOATS + P_K), pf_at + 8 * (law * P_FLOATS + P_D))
        for i in range(3):
            f[F_OUT + i] = f[T2 + i] + pf[law, P_FF + i] - f[T3 + i]
    if s[HAS_GOAL]:
        _check_goal(dot_fn, f, f_at, s, phase, in_place, n_phases)


# _law's pieces, in the order it runs them; inlined like _law itself, so that _step stays
# one body of machine code


@njit(**JIT, inline="always")
def _track_velocity(f, s, dt):
    """The velocity: v = 0.7 v + 0.3 (x - x_prev) / dt, in place, in that order."""
    if s[HAS_PREV]:
        for i in range(3):
            d_x = f[X + i] - f[PREV + i]
            d_x *= 0.3
            d_x /= dt
            f[V + i] *= 0.7
            f[V + i] += d_x
            f[PREV + i] = f[X + i]
    else:
        for i in range(3):
            f[PREV + i] = f[X + i]
        s[HAS_PREV] = 1


@njit(**JIT, inline="always")
def _start_reference(f, pf, pq, law, lead):
    """A law's first reference: half a lead along its direction, at the tool if in place."""
    if law != NONE and not pq[law, Q_IN_PLACE]:
        for i in range(3):
            f[REF + i] = f[X + i] + pf[law, P_DIR + i] * 0.5 * lead
    else:
        for i in range(3):
            f[REF + i] = f[X + i]


@njit(**JIT, inline="always")
def _enter_phase(f, s, pf, pq, phase, law, lead):
    """A new estimated phase: its law starts afresh (``step``'s ``phase != self.phase``)."""
    s[PHASE] = phase
    s[HANDED] = NONE
    s[VISITED] = 0 if phase == NONE or not 0 <= phase < MAX_PHASES else (1 << phase)
    f[STALLED_FOR] = 0.0
    s[HAS_STALL_FROM] = 0
    s[HAS_LAST_D] = 0
    s[AT_PLACE] = 0
    _start_reference(f, pf, pq, law, lead)
    s[HAS_REF] = 1


@njit(**JIT, inline="always")
def _unless_blocked(dot_fn, f, f_at, s, pf, pq, law, phase, dt, lead, n_phases):
    """``ReproductionPolicy._unless_blocked``: (law, phase), the successor's if handed to it."""
    touching = not pq[law, Q_IN_PLACE] and _dot(dot_fn, f_at, FORCE, FORCE) > CONTACT_FORCE ** 2
    if not touching or not s[HAS_STALL_FROM]:
        if touching:
            for i in range(3):
                f[STALL_FROM + i] = f[X + i]
        s[HAS_STALL_FROM] = 1 if touching else 0
        f[STALLED_FOR] = 0.0
    else:
        f[STALLED_FOR] += dt
        if not f[STALLED_FOR] < STALL_TIME:
            d_at = LAST_D if s[HAS_LAST_D] else -1
            for i in range(3):
                f[T1 + i] = f[X + i] - f[STALL_FROM + i]
                f[D + i] = pf[law, P_DIR + i] if d_at < 0 else f[LAST_D + i]
            blocked = _dot(dot_fn, f_at, T1, D) < STALL_SPEED * pf[law, P_SPEED] * f[STALLED_FOR]
            for i in range(3):
                f[STALL_FROM + i] = f[X + i]
            s[HAS_STALL_FROM] = 1
            f[STALLED_FOR] = 0.0
            nxt = pq[law, Q_SUCCESSOR]
            if (blocked and nxt != NONE and 0 <= nxt < n_phases and pq[nxt, Q_VALID]
                    and not (nxt < MAX_PHASES and s[VISITED] & (1 << nxt))):
                s[HANDED] = nxt
                if nxt < MAX_PHASES:
                    s[VISITED] |= 1 << nxt
                s[HAS_LAST_D] = 0
                law = phase = nxt
                s[AT_PLACE] = 0
                _start_reference(f, pf, pq, law, lead)
    return law, phase


@njit(**JIT, inline="always")
def _spring(gemv_fn, f, f_at, k_at, d_at):
    """T2 = K (ref - x) and T3 = D v, for the 3x3 K and D at addresses ``k_at``, ``d_at``."""
    for i in range(3):
        f[T1 + i] = f[REF + i] - f[X + i]
    _gemv(gemv_fn, k_at, f_at + 8 * T1, f_at + 8 * T2)
    _gemv(gemv_fn, d_at, f_at + 8 * V, f_at + 8 * T3)


@njit(**JIT, inline="always")
def _hold_force(gemv_fn, f, f_at):
    """The hold's force: K_hold (ref - x) - D_hold v."""
    _spring(gemv_fn, f, f_at, f_at + 8 * HOLD_K, f_at + 8 * HOLD_D)
    for i in range(3):
        f[F_OUT + i] = f[T2 + i] - f[T3 + i]


@njit(**JIT, inline="always")
def _head_for_aim(dot_fn, f, f_at, pf, law, lead):
    """Free motion into a phase done in place: D towards its aim, the reference keeping
    only its lead along D."""
    for i in range(3):
        f[T1 + i] = pf[law, P_AIM + i] - f[X + i]
    if np.sqrt(_dot(dot_fn, f_at, T1, T1)) > lead:
        norm = np.sqrt(_dot(dot_fn, f_at, T1, T1))
        for i in range(3):
            f[D + i] = f[T1 + i] / norm
        for i in range(3):
            f[T2 + i] = f[REF + i] - f[X + i]
        along = _dot(dot_fn, f_at, T2, D)
        if 0.0 > along:  # Python's max(along, 0.0)
            along = 0.0
        for i in range(3):
            f[REF + i] = f[X + i] + along * f[D + i]


@njit(**JIT, inline="always")
def _along_contact(dot_fn, f, f_at):
    """``ReproductionPolicy._along_contact``: D turned into the surface's plane."""
    fn = np.sqrt(_dot(dot_fn, f_at, FORCE, FORCE))
    if not fn <= CONTACT_FORCE:
        for i in range(3):
            f[T1 + i] = f[FORCE + i] / fn  # n
        into = _dot(dot_fn, f_at, D, T1)
        if not into >= 0.0:
            for i in range(3):
                f[T2 + i] = f[D + i] - into * f[T1 + i]  # t
            tn = np.sqrt(_dot(dot_fn, f_at, T2, T2))
            if not tn < MIN_SLIDE:
                for i in range(3):
                    f[D + i] = f[T2 + i] / tn


@njit(**JIT, inline="always")
def _advance_reference(dot_fn, f, f_at, pf, law, dt, lead):
    """A moving law's reference: on along D at the phase's speed, at most a lead ahead."""
    speed = pf[law, P_SPEED]
    for i in range(3):
        f[REF + i] = f[REF + i] + f[D + i] * speed * dt
    for i in range(3):
        f[T1 + i] = f[REF + i] - f[X + i]
    ahead = _dot(dot_fn, f_at, T1, D)
    if ahead > lead:
        for i in range(3):
            f[REF + i] -= f[D + i] * (ahead - lead)


@njit(**JIT, inline="always")
def _reference_to_place(dot_fn, f, f_at, pf, law, dt, lead):
    """A law done in place: its reference towards the place at PLACE_SPEED, at most a
    lead from the tool."""
    for i in range(3):
        f[T1 + i] = pf[law, P_PLACE + i] - f[REF + i]  # to_place
    norm = np.sqrt(_dot(dot_fn, f_at, T1, T1))
    limit = PLACE_SPEED * dt
    step = limit if limit < norm else norm  # Python's min(norm, limit)
    if step > 0.0:
        scale = step / np.sqrt(_dot(dot_fn, f_at, T1, T1))
        for i in range(3):
            f[REF + i] = f[REF + i] + f[T1 + i] * scale
    for i in range(3):
        f[T2 + i] = f[REF + i] - f[X + i]  # ahead
    if np.sqrt(_dot(dot_fn, f_at, T2, T2)) > lead:
        scale = lead / np.sqrt(_dot(dot_fn, f_at, T2, T2))
        for i in range(3):
            f[REF + i] = f[X + i] + f[T2 + i] * scale


@njit(**JIT, inline="always")
def _at_place(dot_fn, f, f_at, pf, law, lead):
    """Whether the reference has arrived at the law's place and the tool is within a lead of it."""
    for i in range(3):
        f[T1 + i] = pf[law, P_PLACE + i] - f[REF + i]
    there = np.sqrt(_dot(dot_fn, f_at, T1, T1)) < 1e-6
    if there:
        for i in range(3):
            f[T2 + i] = pf[law, P_PLACE + i] - f[X + i]
        there = np.sqrt(_dot(dot_fn, f_at, T2, T2)) < lead
    return there


@njit(**JIT, inline="always")
def _check_goal(dot_fn, f, f_at, s, phase, in_place, n_phases):
    """At the goal (near it, or past it in the last phase): GOAL_REACHED, the reference at the tool."""
    for i in range(3):
        f[T1 + i] = f[X + i] - f[GOAL + i]
    near = np.sqrt(_dot(dot_fn, f_at, T1, T1)) < f[TOL]
    if near or phase == n_phases - 1:
        along = _dot(dot_fn, f_at, T1, D)
        past = not in_place and along >= 0.0
        for i in range(3):
            f[T2 + i] = f[T1 + i] - along * f[D + i]
        lateral = np.sqrt(_dot(dot_fn, f_at, T2, T2))
        if near or (past and lateral < 3 * f[TOL]):
            s[GOAL_REACHED] = 1
            for i in range(3):
                f[REF + i] = f[X + i]


_STEP = []  # _step's machine code, compiled (or loaded from numba's cache) by the first policy


def _step_entry():
    if not _STEP:
        _STEP.append(entry(_step, "int64, int64, int64, int64, int64, int64, int64"))
    return _STEP[0]


class CompiledPolicy(HoldsAddresses):
    """A ``ReproductionPolicy`` (built the same way, its attributes read the same) whose
    ``step`` runs in ``_step``.  Only for policies without turning (``compilable``)."""

    def __init__(self, policy: ReproductionPolicy):
        if not compilable(policy):
            raise ValueError("a policy whose phases turn, or with a goal rotation, runs in Python")
        self._python = policy
        n = len(policy.phases)
        self._f = np.zeros(N_FLOAT)
        self._s = np.zeros(N_INT, dtype=np.int64)
        self._pf = np.zeros((max(n, 1), P_FLOATS))
        self._pq = np.zeros((max(n, 1), P_INTS), dtype=np.int64)
        for p, law in enumerate(policy.phases):
            if law is None:
                continue
            row = self._pf[p]
            row[P_DIR:P_DIR + 3] = law.direction
            row[P_K:P_K + 9] = np.ascontiguousarray(law.stiffness).ravel()
            row[P_D:P_D + 9] = np.ascontiguousarray(law.damping).ravel()
            row[P_FF:P_FF + 3] = law.feedforward
            row[P_SPEED] = law.speed
            if law.place is not None:
                row[P_PLACE:P_PLACE + 3] = law.place
            if law.aim is not None:
                row[P_AIM:P_AIM + 3] = law.aim
            self._pq[p] = (1, law.in_place, law.place is not None, law.aim is not None, law.free,
                           NONE if law.successor is None else law.successor)
        f, s = self._f, self._s
        f[TOL], f[LEAD] = policy.tol, policy.lead
        f[HOLD_K:HOLD_K + 9] = np.ascontiguousarray(policy.hold_stiffness).ravel()
        f[HOLD_D:HOLD_D + 9] = np.ascontiguousarray(policy.hold_damping).ravel()
        if policy.goal is not None:
            f[GOAL:GOAL + 3] = policy.goal
            s[HAS_GOAL] = 1
        self._n = n
        self._at = (address(f), self._s.ctypes.data, address(self._pf), self._pq.ctypes.data)
        # here, not at the first step: a commander builds its policy before the episode's first cycle
        self._kernel = _step_entry()
        self.goal = policy.goal
        self.phases = policy.phases
        self.reset()

    def reset(self) -> None:
        s, f = self._s, self._f
        for k in (HAS_REF, HAS_PREV, HAS_STALL_FROM, HAS_LAST_D, VISITED, AT_PLACE, GOAL_REACHED):
            s[k] = 0
        s[PHASE] = s[HANDED] = s[APPLIED] = NONE
        f[STATE:] = 0.0
        self.R_hold = None

    def step(self, x: np.ndarray, R: np.ndarray, phase: int | None, dt: float = CYCLE,
             force: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``ReproductionPolicy.step``: the same arguments, the same numbers."""
        f, s = self._f, self._s
        if self.R_hold is None:
            self.R_hold = R.copy()
        f[X:X + 3] = x
        if force is not None:
            f[FORCE:FORCE + 3] = force
        s[HAS_FORCE] = force is not None
        f[DT] = dt
        s[PHASE_IN] = NONE if phase is None else phase
        s[TOOL_FRAME] = 0
        self._kernel(blas.DOT, blas.GEMV, *self._at, self._n)
        return f[F_OUT:F_OUT + 3].copy(), self.R_hold

    def tool_step(self, pose, tool_force, phase: int | None, dt: float = CYCLE):
        """``ReproductionPolicy.tool_step``: the same arguments, the same numbers."""
        f, s = self._f, self._s
        f[POSE:POSE + 12] = pose
        f[TOOL_FORCE:TOOL_FORCE + 3] = tool_force
        if self.R_hold is None:
            self.R_hold = f[POSE:POSE + 12].reshape(3, 4)[:, :3].copy()
        s[HAS_FORCE] = 1
        f[DT] = dt
        s[PHASE_IN] = NONE if phase is None else phase
        s[TOOL_FRAME] = 1
        self._kernel(blas.DOT, blas.GEMV, *self._at, self._n)
        return f[TOOL_F_OUT:TOOL_F_OUT + 3].copy(), self.R_hold, f[X:X + 3].copy()

    # what the commander and the tests read of a policy's state
    @property
    def goal_reached(self) -> bool:
        return bool(self._s[GOAL_REACHED])

    @property
    def applied(self) -> int | None:
        a = int(self._s[APPLIED])
        return None if a == NONE else a

    @property
    def phase(self) -> int | None:
        p = int(self._s[PHASE])
        return None if p == NONE else p

    @property
    def ref(self) -> np.ndarray | None:
        return self._f[REF:REF + 3].copy() if self._s[HAS_REF] else None

    @property
    def v(self) -> np.ndarray:
        return self._f[V:V + 3].copy()


def compilable(policy: ReproductionPolicy) -> bool:
    """Whether ``CompiledPolicy`` can run ``policy``: no turning, few enough phases, and
    numpy's BLAS reachable from a kernel."""
    return (blas.AVAILABLE and policy.goal_rotation is None and len(policy.phases) <= MAX_PHASES
            and not any(law is not None and law.turns for law in policy.phases))


def compiled_policy(policy: ReproductionPolicy):
    """``policy`` compiled where ``compilable``, else ``policy`` itself."""
    return CompiledPolicy(policy) if compilable(policy) else policy
