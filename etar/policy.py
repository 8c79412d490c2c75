"""The reproduction policy: the learned per-phase Cartesian impedance, applied.

Given the phase the online filter believes in, the policy turns each phase's
learned impedance (``etar.impedance.PhaseImpedance``: direction d, compliant
axes, K = R V R^T, mean contact force) into the force the controller should
exert this cycle.  It moves a reference point along d at the phase's
demonstrated speed (never more than ``lead`` ahead of the tool, so a blocked
tool does not wind the spring up) and returns

    F = K (x_ref - x) + F_ff - D v,   F_ff = -(mean contact force on the compliant axes)

i.e. stiff along d and the other non-compliant axes, soft along the compliant
axes, pressing into the surfaces as the teacher did.  At the goal (the
demonstrations' mean end point) the reference stops and ``goal_reached`` is set.

With a pose state each phase also has its mean angular velocity, and the task
the demonstrations' mean final turn (``goal_rotation``).  A turning phase turns
the setpoint orientation at its rate, never more than ``ROT_LEAD`` ahead of the
tool and never past the goal's turn; the goal then also needs the turn.  A phase
done in place (``in_place``: the coupler's press and turn) has no direction to
follow: its reference goes, stiffly, to where the demonstrations did it, and
there the phase's law presses along its compliant axis as the teacher did.

Pure numpy: no messaging, no simulator, no clock (``step`` is told ``dt``).
The impedance commander (``services``) wraps it; tests drive it directly.  It runs
``step`` compiled where it can (``etar.policy_kernel``: the same numbers); any change
here is a change there, which ``tests/etar/test_policy_kernel.py`` catches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from etar.impedance import PhaseImpedance, impedance_from_file

# s: one KRC cycle, a step's default dt.  The cycle's home is robot_sim.cycle.FRI_CYCLE_NS,
# but etar imports neither robot_sim nor services: the commander passes the cycle it runs at
DT = 0.001
HOLD_STIFFNESS = 2000.0  # N/m on every axis: before any phase, at the goal, on the way to a place
EFFECTIVE_MASS = 2.0  # kg, for the damping ratio of the commanded impedance
# rad: the setpoint orientation turns at most this far ahead of the tool, 15 Nm at the
# commander's 150 Nm/rad: enough to turn against a seal's friction, bounded if stuck
ROT_LEAD = 0.1
ROT_TOLERANCE = 0.1  # rad: how close to the goal's turn counts as there
TURNING_RATE = 1e-3  # rad/s: a phase with a slower mean angular velocity does not turn
PLACE_SPEED = 0.02  # m/s: how fast a phase done in place moves its reference to where it was demonstrated
# m: the stiff axis pushes a blocked tool with at most K lead: 10 N at 2000 N/m, the
# order of the demonstrated contact forces.  With 2 cm (40 N) the free-motion law slid
# the tool down the plate faster than any demonstration, and the estimator, which
# judges phases by their dynamics, flickered between free motion and plate.
LEAD = 0.005
# N: a measured contact force above this is a surface the tool touches (as in
# etar.impedance.derive_impedance's ``contact_force``)
CONTACT_FORCE = 2.0
# a phase demonstrated in free space slides along a surface it meets only when at
# least this much of its direction lies along the surface (sin 17 deg); a direction
# (nearly) straight into it is the phase's end: it keeps pressing, so that the
# estimator sees the contact it was taught to switch on
MIN_SLIDE = 0.3
# s: a moving phase whose tool touches something and makes less than STALL_SPEED of
# its speed along its direction for this long is blocked: the law goes on with the
# phase the demonstrations entered next (``PhaseImpedance.successor``) until the
# estimator names another phase.  The estimator judges phases by their dynamics, so it
# cannot see the next phase begin while the tool stands still in a corner the current
# law drives it into (two-sided valley: a plate's law at the groove's bottom)
STALL_TIME = 0.5
STALL_SPEED = 0.2


def exp3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (Rodrigues)."""
    theta = math.sqrt(float(w @ w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + (math.sin(theta) / theta) * K + ((1.0 - math.cos(theta)) / theta ** 2) * K @ K


def log3(R: np.ndarray) -> np.ndarray:
    """Rotation vector of the rotation matrix ``R`` (the inverse of ``exp3`` for angles < pi)."""
    c = min(1.0, max(-1.0, 0.5 * (float(np.trace(R)) - 1.0)))
    theta = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-6:
        return 0.5 * v
    if math.pi - theta < 1e-6:
        # near a half turn the antisymmetric part vanishes: the axis from R + I
        M = 0.5 * (R + np.eye(3))
        axis = M[:, int(np.argmax(np.diag(M)))]
        return theta * axis / np.linalg.norm(axis)
    return (theta / (2.0 * math.sin(theta))) * v


@dataclass(frozen=True)
class PhaseLaw:
    """One phase's impedance as the arrays a cycle needs, prepared once."""

    direction: np.ndarray  # (3,)
    stiffness: np.ndarray  # (3, 3) K = R V R^T
    damping: np.ndarray  # (3, 3)
    feedforward: np.ndarray  # (3,) -(mean contact force on the compliant axes)
    speed: float  # m/s along the direction
    angular_velocity: np.ndarray  # (3,) rad/s, axes of the episode's first orientation
    in_place: bool  # demonstrated without going anywhere: go to where it happened and stay
    place: np.ndarray | None  # (3,) the demonstrations' mean position in this phase
    aim: np.ndarray | None  # (3,) free motion into a phase done in place: head for its place
    turns: bool  # the angular velocity is not zero
    free: bool  # demonstrated in free space: no compliant axis, not done in place
    successor: int | None  # the phase the demonstrations most often entered from this one


def _impedance(imp) -> PhaseImpedance | None:
    if imp is None or isinstance(imp, PhaseImpedance):
        return imp
    return impedance_from_file(imp)


class ReproductionPolicy:
    """The per-phase law of one reproduction (``reset`` before the next)."""

    def __init__(self, impedances, goal=None, *, lead: float = LEAD, damping_ratio: float = 0.7,
                 goal_tolerance: float = 0.01, goal_rotation=None, rotation_tolerance: float = ROT_TOLERANCE):
        self.zeta = damping_ratio
        imps = [_impedance(i) for i in impedances]
        self.phases = [None if imp is None else self._prepare(imp, imps) for imp in imps]
        self.hold_stiffness = HOLD_STIFFNESS * np.eye(3)
        self.hold_damping = self._damping(self.hold_stiffness)
        self.goal = None if goal is None else np.asarray(goal, dtype=np.float64)
        # the goal's turn counts only if the demonstrations turned noticeably
        self.goal_rotation = None
        if goal_rotation is not None and np.linalg.norm(goal_rotation) > rotation_tolerance:
            self.goal_rotation = np.asarray(goal_rotation, dtype=np.float64)
            self._goal_turn_T = exp3(self.goal_rotation).T
        self.lead = lead
        self.tol = goal_tolerance
        self.rot_tol = rotation_tolerance
        self.reset()

    def _prepare(self, imp: PhaseImpedance, impedances: list) -> PhaseLaw:
        K = np.asarray(imp.stiffness, dtype=np.float64)
        F_ff = np.zeros(3)
        for a in np.asarray(imp.compliant_axes, dtype=np.float64).reshape(-1, 3):
            F_ff -= (imp.mean_force @ a) * a
        omega = np.asarray(imp.angular_velocity, dtype=np.float64)
        if np.linalg.norm(omega) < TURNING_RATE:
            omega = np.zeros(3)
        in_place = bool(imp.in_place)
        # free motion whose successor is done in place (the coupler's approach) heads for
        # that place: a fixed direction from another start would miss a 36 mm socket
        aim = None
        nxt = imp.successor
        if not in_place and imp.n_compliant == 0 and nxt is not None and 0 <= nxt < len(impedances):
            follow = impedances[nxt]
            if follow is not None and follow.in_place and follow.mean_position is not None:
                aim = np.asarray(follow.mean_position, dtype=np.float64)
        place = None if imp.mean_position is None else np.asarray(imp.mean_position, dtype=np.float64)
        return PhaseLaw(np.asarray(imp.direction, dtype=np.float64), K, self._damping(K), F_ff,
                        max(float(imp.mean_speed), 0.01), omega, in_place, place, aim, bool(omega.any()),
                        imp.n_compliant == 0 and not in_place, imp.successor)

    def reset(self) -> None:
        self.phase = None
        self.ref = None
        self.R_hold = None
        self.turn_ref = np.zeros(3)  # setpoint orientation: R_hold exp(turn_ref); kept across phases
        self.turned_setpoint = False  # turn_ref is not zero
        self.at_place = False  # a phase done in place: its tool has arrived where it was demonstrated
        self.prev_x = None
        self.v = np.zeros(3)
        self._scratch = np.zeros(3)
        self.goal_reached = False
        self.applied = None  # the phase whose law made the last step's force (None: the hold law)
        self.handed = None  # the successor phase whose law runs while the estimate's is blocked
        self.visited = set()  # phases handed over to since the estimate last changed
        self.stalled_for = 0.0  # s since stall_from: the window over which progress is judged
        self.stall_from = None  # where the tool was when the window began (None: not touching)
        self.last_d = None  # the running law's direction last cycle (after aim and contact)

    def _setpoint_rotation(self) -> np.ndarray:
        if not self.turned_setpoint:
            return self.R_hold
        return self.R_hold @ exp3(self.turn_ref)

    def _turn(self, law: PhaseLaw, turned: np.ndarray, dt: float) -> None:
        """Advance the setpoint's turn at the phase's rate: at most ROT_LEAD ahead of
        the tool's ``turned`` (rotation vector from R_hold), never past the goal's."""
        w = law.angular_velocity
        self.turn_ref = self.turn_ref + w * dt
        ahead = self.turn_ref - turned
        if np.linalg.norm(ahead) > ROT_LEAD:
            self.turn_ref = turned + ahead * (ROT_LEAD / np.linalg.norm(ahead))
        if self.goal_rotation is not None:
            axis = w / np.linalg.norm(w)
            beyond = (self.turn_ref - self.goal_rotation) @ axis
            if beyond > 0.0:
                self.turn_ref = self.turn_ref - beyond * axis
        self.turned_setpoint = bool(self.turn_ref.any())

    def _turned_enough(self, turned: np.ndarray) -> bool:
        if self.goal_rotation is None:
            return True
        return bool(np.linalg.norm(log3(self._goal_turn_T @ exp3(turned))) < self.rot_tol)

    def tool_step(self, pose, tool_force, phase: int | None, dt: float = DT):
        """``step`` for a controller that speaks in the tool's frame, as the KRC's Cartesian
        impedance does: ``pose`` the measured tool pose as 12 numbers, the rows of
        [R | x] (base axes); ``tool_force`` the measured external force (3,) in tool axes.
        Returns (the force to add (3,), tool axes; the setpoint rotation; the tool's
        position x (3,))."""
        m = np.array(pose).reshape(3, 4)
        R, x = m[:, :3], m[:, 3]
        force = R @ np.asarray(tool_force, dtype=np.float64)
        F, R_set = self.step(x, R, phase, dt, force)
        return R.T @ F, R_set, x

    def step(self, x: np.ndarray, R: np.ndarray, phase: int | None, dt: float = DT,
             force: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(force in base axes (3,), setpoint rotation) for this cycle; ``dt``: time since
        the previous step (more than one cycle when realtime left measurements unanswered);
        ``force``: the measured external force on the tool, base axes (None: not known)."""
        if self.R_hold is None:
            self.R_hold = R.copy()
        if self.prev_x is not None:
            # a light low-pass on the finite-difference velocity (1 ms steps):
            # v = 0.7 v + 0.3 (x - x_prev) / dt, in place, in that order
            d_x = self._scratch
            np.subtract(x, self.prev_x, out=d_x)
            d_x *= 0.3
            d_x /= dt
            self.v *= 0.7
            self.v += d_x
            self.prev_x[:] = x
        else:
            self.prev_x = x.copy()
        law = self.phases[phase] if phase is not None and 0 <= phase < len(self.phases) else None
        if phase != self.phase:
            # a new phase starts its reference at the tool, already half a lead
            # ahead along its direction: a flickering estimate must not stall the motion
            self.phase = phase
            self.handed = None
            self.visited = set() if phase is None else {phase}
            self.stalled_for = 0.0
            self.stall_from = None
            self.last_d = None
            self.at_place = False
            moving = law is not None and not law.in_place
            self.ref = x + law.direction * 0.5 * self.lead if moving else x.copy()
        if self.handed is not None:
            phase, law = self.handed, self.phases[self.handed]
        if law is not None and force is not None and not self.goal_reached:
            law, phase = self._unless_blocked(x, law, phase, force, dt)
        self.applied = None if self.goal_reached or law is None else phase
        if self.goal_reached or law is None:
            if self.ref is None:
                self.ref = x.copy()
            return self.hold_stiffness @ (self.ref - x) - self.hold_damping @ self.v, self._setpoint_rotation()
        d = law.direction
        if law.aim is not None and np.linalg.norm(law.aim - x) > self.lead:
            # free space: K is isotropic, so turning d changes nothing else; the
            # reference keeps only its lead along the new d
            d = (law.aim - x) / np.linalg.norm(law.aim - x)
            self.ref = x + max((self.ref - x) @ d, 0.0) * d
        if law.free and law.aim is None and force is not None:
            # (a phase aiming for its successor's place is meant to arrive and press there:
            # sliding the coupler's approach off the socket delayed the switch, 6-8 s -> 8-10.5 s)
            d = self._along_contact(x, d, force)
        self.last_d = d
        if not law.in_place:
            self.ref = self.ref + d * law.speed * dt
            ahead = (self.ref - x) @ d
            if ahead > self.lead:
                self.ref -= d * (ahead - self.lead)
        elif law.place is not None:
            # towards where the phase was demonstrated, at most a lead ahead of the tool
            to_place = law.place - self.ref
            step = min(np.linalg.norm(to_place), PLACE_SPEED * dt)
            if step > 0.0:
                self.ref = self.ref + to_place * (step / np.linalg.norm(to_place))
            ahead = self.ref - x
            if np.linalg.norm(ahead) > self.lead:
                self.ref = x + ahead * (self.lead / np.linalg.norm(ahead))
        going = law.in_place and law.place is not None and not self.at_place
        if going:
            self.at_place = bool(np.linalg.norm(law.place - self.ref) < 1e-6
                                 and np.linalg.norm(law.place - x) < self.lead)
            going = not self.at_place
        if going:
            # on the way to the place: stiff and damped on every axis, no push, so the
            # tool arrives at the reference's pace (dropping off a rim onto the floor
            # under the phase's push along a soft axis hit it with 70 N); the phase's own
            # law, with its push, starts there
            F = self.hold_stiffness @ (self.ref - x) - self.hold_damping @ self.v
        else:
            F = law.stiffness @ (self.ref - x) + law.feedforward - law.damping @ self.v
        turned = None
        if law.turns or self.goal_rotation is not None:
            turned = log3(self.R_hold.T @ R)
            if law.turns:
                self._turn(law, turned, dt)
        # at the goal counts in any phase: a model with more phases than the task's
        # (pooled BIC on the two-sided valley: 6, two of them the groove) may name another
        # than the last there, and the tool ran on past the goal into a joint limit
        near = self.goal is not None and np.linalg.norm(x - self.goal) < self.tol
        if self.goal is not None and (near or phase == len(self.phases) - 1):
            past = not law.in_place and (x - self.goal) @ d >= 0.0
            lateral = np.linalg.norm((x - self.goal) - ((x - self.goal) @ d) * d)
            there = near or (past and lateral < 3 * self.tol)
            if there and (turned is None or self._turned_enough(turned)):
                self.goal_reached = True
                self.ref = x.copy()
        return F, self._setpoint_rotation()

    def _unless_blocked(self, x: np.ndarray, law: PhaseLaw, phase: int, force: np.ndarray, dt: float):
        """(law, phase) to run: the successor's once ``law``'s tool, touching something,
        has gone less than STALL_SPEED of the phase's speed along its direction over
        STALL_TIME (measured over the window, not from the velocity: a tool pressed into
        a corner chatters)."""
        touching = not law.in_place and float(force @ force) > CONTACT_FORCE ** 2
        if not touching or self.stall_from is None:
            self.stall_from, self.stalled_for = (x.copy() if touching else None), 0.0
            return law, phase
        self.stalled_for += dt
        if self.stalled_for < STALL_TIME:
            return law, phase
        d = law.direction if self.last_d is None else self.last_d
        blocked = float((x - self.stall_from) @ d) < STALL_SPEED * law.speed * self.stalled_for
        self.stall_from, self.stalled_for = x.copy(), 0.0
        nxt = law.successor
        if (not blocked or nxt is None or not 0 <= nxt < len(self.phases) or self.phases[nxt] is None
                or nxt in self.visited):
            return law, phase
        self.handed = nxt
        self.visited.add(nxt)
        self.last_d = None
        law = self.phases[nxt]
        self.at_place = False
        self.ref = x + law.direction * 0.5 * self.lead if not law.in_place else x.copy()
        return law, nxt

    def _along_contact(self, x: np.ndarray, d: np.ndarray, force: np.ndarray) -> np.ndarray:
        """A free-space phase's direction where the tool touches a surface: the
        component into the surface (against the measured contact force) removed, so
        the tool slides along it instead of stalling against it.  The learned
        direction is one world direction; a phase whose demonstrations met surfaces
        on different sides (the valley's plates: their contact forces mirror each
        other) holds on none of them, and its law pushed the tool into a plate it
        could not move along (two-sided valley, 3 phases: 19 of 20 stalled).  The
        reference keeps what lead into the surface it has (at most ``lead``: 10 N at
        2000 N/m): the tool slides on pressing, as the teacher did, and the estimator
        sees the contact force its transition into the surface's phase was learned
        on.  Without that push the estimate held free motion on a plate for up to 3 s;
        pressing in place before sliding cost the two-sided valley's left plate
        instead (the three versions measured: docs/learning.md, the reproduction
        policy)."""
        fn = math.sqrt(float(force @ force))
        if fn <= CONTACT_FORCE:
            return d
        n = force / fn
        into = float(d @ n)
        if into >= 0.0:
            return d
        t = d - into * n
        tn = math.sqrt(float(t @ t))
        if tn < MIN_SLIDE:
            return d
        return t / tn

    def _damping(self, K):
        w, V = np.linalg.eigh(0.5 * (K + K.T))
        c = 2.0 * self.zeta * np.sqrt(np.maximum(w, 0.0) * EFFECTIVE_MASS)
        return V @ np.diag(c) @ V.T
