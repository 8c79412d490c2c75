"""Per-phase Cartesian impedance from demonstration data.

The geometric approach of Suomalainen & Kyrki (Humanoids 2017): the robot is
driven along a desired direction d by an impedance controller; where a surface
is touched, the contact force f deflects the motion, so the measured velocity v
lies in the plane spanned by d and f.  Every in-contact sample therefore
constrains d to be orthogonal to n_t = v_t x f_t, and d is the direction most
orthogonal to all n_t (smallest right singular vector).  Motion not along d is
attributed to contact: the directions of the contact force orthogonal to d are
the compliant axes (0 in free space, 1 on a plane, 2 in a groove), and the
stiffness is K = R V R^T with R = [d, c_1, c_2] and V = diag(stiff, soft/stiff...).
(Thesis eq. 77-78.)

Where the state carries the orientation (``pose``: a rotation vector relative to
the episode's first orientation), each phase also gets its mean angular
velocity, so that a phase that turns the tool (the hose coupler's coupling) can
be reproduced turning.  The rate is the finite difference of the rotation
vector, exact for a turn about one fixed axis, as in that task.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

# m/s: a phase whose mean velocity is slower than this is done in place; the
# demonstrated motions are 4-5 cm/s, a hand holding still drifts by a few mm/s
IN_PLACE_SPEED = 0.005


@dataclass(frozen=True)
class PhaseImpedance:
    direction: np.ndarray  # (3,) unit desired direction of motion d
    n_compliant: int  # 0, 1 or 2
    compliant_axes: np.ndarray  # (n_compliant, 3) unit vectors orthogonal to d
    rotation: np.ndarray  # (3, 3) R = [d, c_1, c_2] (columns), right-handed
    stiffness: np.ndarray  # (3, 3) K = R V R^T, N/m
    mean_force: np.ndarray  # (3,) mean measured contact force of the phase, N
    mean_speed: float  # m/s along d
    n_samples: int
    n_contact_samples: int
    # (3,) mean angular velocity, rad/s, in the axes of the episode's first
    # orientation; zero when the state has no orientation
    angular_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    # (3,) mean position of the phase's samples (where a phase done in place happens); None if not given
    mean_position: np.ndarray | None = None
    in_place: bool = False  # demonstrated without going anywhere (press, turn): no direction of motion
    successor: int | None = None  # the phase the demonstrations most often entered from this one

    def to_dict(self) -> dict:
        return dict(
            direction=self.direction.tolist(), n_compliant=self.n_compliant,
            compliant_axes=self.compliant_axes.tolist(), rotation=self.rotation.tolist(),
            stiffness=self.stiffness.tolist(), mean_force=self.mean_force.tolist(),
            mean_speed=self.mean_speed, n_samples=self.n_samples, n_contact_samples=self.n_contact_samples,
            angular_velocity=self.angular_velocity.tolist(),
            mean_position=None if self.mean_position is None else self.mean_position.tolist(),
            in_place=self.in_place, successor=self.successor,
        )

    @classmethod
    def from_dict(cls, data: dict) -> "PhaseImpedance":
        arr = lambda k, shape=None: np.asarray(data[k], dtype=np.float64).reshape(shape) if shape else np.asarray(data[k], dtype=np.float64)  # noqa: E731
        return cls(
            direction=arr("direction"), n_compliant=int(data["n_compliant"]),
            compliant_axes=arr("compliant_axes", (int(data["n_compliant"]), 3)),
            rotation=arr("rotation"), stiffness=arr("stiffness"), mean_force=arr("mean_force"),
            mean_speed=float(data["mean_speed"]), n_samples=int(data["n_samples"]),
            n_contact_samples=int(data["n_contact_samples"]),
            # model files written before orientation was learned have none
            angular_velocity=arr("angular_velocity") if "angular_velocity" in data else np.zeros(3),
            mean_position=arr("mean_position") if data.get("mean_position") is not None else None,
            in_place=bool(data.get("in_place", False)),
            successor=None if data.get("successor") is None else int(data["successor"]),
        )


def impedance_from_file(data: dict) -> PhaseImpedance:
    """A phase's impedance as a model file stores it.  Files written before
    ``in_place`` was learned do not say: such a phase counts as done in place when
    its speed along d is below IN_PLACE_SPEED."""
    imp = PhaseImpedance.from_dict(data)
    if "in_place" not in data:
        imp = replace(imp, in_place=imp.mean_speed < IN_PLACE_SPEED)
    return imp


def _complete_basis(d: np.ndarray, hint: np.ndarray | None = None) -> np.ndarray:
    """Right-handed orthonormal [d, c1, c2]; c1 follows ``hint`` where given."""
    if hint is None or np.linalg.norm(hint - (hint @ d) * d) < 1e-9:
        hint = np.eye(3)[np.argmin(np.abs(d))]
    c1 = hint - (hint @ d) * d
    c1 /= np.linalg.norm(c1)
    c2 = np.cross(d, c1)
    return np.column_stack([d, c1, c2])


def _stiffness(R: np.ndarray, n_compliant: int, stiff: float, soft: float) -> np.ndarray:
    """K = R V R^T (symmetrised), V = diag(stiff, soft for the n_compliant axes after d, stiff)."""
    V = np.full(3, stiff)
    V[1 : 1 + n_compliant] = soft
    K = R @ np.diag(V) @ R.T
    return 0.5 * (K + K.T)


def _in_place_impedance(v, f, fnorm, contact_force, min_contact_fraction, stiffness, compliant_stiffness,
                        omega, where) -> PhaseImpedance:
    """``derive_impedance`` of a phase done in place (pressing, turning): there is no
    direction of motion to find, so the contact force's direction is the compliant
    axis and the others are stiff."""
    contact = fnorm > contact_force
    if contact.sum() < max(3, min_contact_fraction * len(v)):
        contact[:] = False
    mean_f = f[contact].mean(axis=0) if contact.any() else np.zeros(3)
    axes = np.zeros((0, 3))
    if np.linalg.norm(mean_f) > contact_force:
        n = mean_f / np.linalg.norm(mean_f)
        axes = n[None, :]
        R = _complete_basis(_complete_basis(n)[:, 1], n)
    else:
        R = np.eye(3)
    return PhaseImpedance(
        direction=R[:, 0].copy(), n_compliant=len(axes), compliant_axes=R[:, 1 : 1 + len(axes)].T.copy(),
        rotation=R, stiffness=_stiffness(R, len(axes), stiffness, compliant_stiffness), mean_force=mean_f, mean_speed=0.0, n_samples=int(v.shape[0]),
        n_contact_samples=int(contact.sum()), angular_velocity=omega, mean_position=where, in_place=True,
    )


def _direction_in_contact(v, f, speed, fnorm, contact, v_hat) -> np.ndarray:
    """The desired direction d: the direction most orthogonal to every in-contact
    sample's v x f, where the samples decide it; else the mean velocity ``v_hat``."""
    d = v_hat
    if contact.sum() >= 3:
        vn = v[contact] / speed[contact, None]
        fn = f[contact] / fnorm[contact, None]
        normals = np.cross(vn, fn)
        # thin: sv and vt are the full one's, bit for bit (LAPACK factors the same R), without
        # the (samples x samples) U it would build and throw away (1.6 s of the valley's learning)
        _, sv, vt = np.linalg.svd(normals, full_matrices=False)
        sv = np.concatenate([sv, np.zeros(3 - len(sv))])
        # when every sample spans (nearly) the same plane - straight sliding
        # on one surface - d is only known to lie in that plane, and the
        # smallest singular vector is decided by noise: keep the mean
        # velocity, which lies in the plane.  The contact deflects the motion
        # from d by less than 45 degrees in any task we can learn from, so a
        # candidate further from the motion than that is noise too.
        candidate = vt[2] if vt[2] @ v_hat >= 0 else -vt[2]
        if sv[1] > 0.3 * max(sv[0], 1e-12) and candidate @ v_hat > np.cos(np.pi / 4):
            d = candidate
    return d


def _compliant_axes(f, contact, d, contact_force, compliance_ratio) -> np.ndarray:
    """(0, 1 or 2, 3): the contact force directions orthogonal to d, the first
    pointing with the mean such force."""
    axes = np.zeros((0, 3))
    if contact.sum() >= 3:
        fp = f[contact] - np.outer(f[contact] @ d, d)
        fp_norm = np.linalg.norm(fp, axis=1)
        keep = fp_norm > 0.25 * contact_force
        if keep.sum() >= 3:
            u = fp[keep] / fp_norm[keep, None]
            _, sv, vt = np.linalg.svd(u, full_matrices=False)
            k = 1 + int(len(sv) > 1 and sv[1] >= compliance_ratio * sv[0])
            axes = vt[:k]
            # orthogonalise against d (numerical hygiene; they already are)
            axes = axes - np.outer(axes @ d, d)
            axes /= np.linalg.norm(axes, axis=1, keepdims=True)
            mean_fp = fp[keep].mean(axis=0)
            if axes[0] @ mean_fp < 0:
                axes[0] = -axes[0]
    return axes


def derive_impedance(
    velocities,
    forces,
    *,
    contact_force: float = 2.0,
    min_speed_fraction: float = 0.2,
    compliance_ratio: float = 0.25,
    min_contact_fraction: float = 0.5,
    stiffness: float = 2000.0,
    compliant_stiffness: float = 100.0,
    angular_velocities=None,
    positions=None,
    in_place_speed: float = IN_PLACE_SPEED,
) -> PhaseImpedance:
    """Desired direction, compliant axes and K = R V R^T of one phase.

    ``velocities`` (T, 3) m/s and ``forces`` (T, 3) N (the force the environment
    exerts on the tool, as an F/T sensor measures it), same frame.
    Samples with |f| < ``contact_force`` count as free motion; samples slower
    than ``min_speed_fraction`` of the median speed carry no direction.  A
    second compliant axis is kept when its singular value is at least
    ``compliance_ratio`` of the first.  A phase is in contact only if at least
    ``min_contact_fraction`` of its moving samples touch: a free-motion phase's
    few touching samples are the next phase's first ones (a segmentation's
    boundary is uncertain by a few samples), and their force must not become
    a compliant axis and a feedforward push in free space.  Stiffness:
    ``stiffness`` along d and the non-compliant axes, ``compliant_stiffness``
    along compliant axes.  ``angular_velocities`` (T, 3) rad/s, optional: their
    mean over the phase is its ``angular_velocity``.  ``positions`` (T, 3) m,
    optional: their mean is its ``mean_position``.  A phase whose mean velocity
    is below ``in_place_speed`` is done in place (``in_place``): it has no
    direction of motion; its compliant axis is the mean contact force's
    direction, and ``direction`` is just the first stiff axis.
    """
    v = np.asarray(velocities, dtype=np.float64)
    f = np.asarray(forces, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or f.shape != v.shape:
        raise ValueError(f"velocities and forces must both be (T, 3), got {v.shape} and {f.shape}")
    if v.shape[0] < 2:
        raise ValueError(f"a phase needs at least 2 samples to derive an impedance, got {v.shape[0]}")
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(f))):
        raise ValueError("velocities and forces must be finite")
    omega = np.zeros(3)
    if angular_velocities is not None:
        w = np.asarray(angular_velocities, dtype=np.float64)
        if w.shape != v.shape:
            raise ValueError(f"angular_velocities must be (T, 3) like velocities {v.shape}, got {w.shape}")
        if not np.all(np.isfinite(w)):
            raise ValueError("angular_velocities must be finite")
        omega = w.mean(axis=0)
    where = None
    if positions is not None:
        x = np.asarray(positions, dtype=np.float64)
        if x.shape != v.shape or not np.all(np.isfinite(x)):
            raise ValueError(f"positions must be finite and (T, 3) like velocities {v.shape}, got {x.shape}")
        where = x.mean(axis=0)
    speed = np.linalg.norm(v, axis=1)
    fnorm = np.linalg.norm(f, axis=1)
    if np.linalg.norm(v.mean(axis=0)) < in_place_speed:
        return _in_place_impedance(v, f, fnorm, contact_force, min_contact_fraction, stiffness, compliant_stiffness,
                                   omega, where)
    moving = speed > min_speed_fraction * max(np.median(speed), 1e-12)
    contact = (fnorm > contact_force) & moving
    if contact.sum() < min_contact_fraction * max(moving.sum(), 1):
        contact[:] = False
    mean_v = v[moving].mean(axis=0) if moving.any() else v.mean(axis=0)
    if np.linalg.norm(mean_v) < 1e-12:
        raise ValueError("the phase does not move: no direction of motion can be derived")
    v_hat = mean_v / np.linalg.norm(mean_v)
    d = _direction_in_contact(v, f, speed, fnorm, contact, v_hat)
    axes = _compliant_axes(f, contact, d, contact_force, compliance_ratio)
    R = _complete_basis(d, axes[0] if len(axes) else None)
    return PhaseImpedance(
        direction=d, n_compliant=len(axes), compliant_axes=R[:, 1 : 1 + len(axes)].T.copy(), rotation=R,
        stiffness=_stiffness(R, len(axes), stiffness, compliant_stiffness), mean_force=f[contact].mean(axis=0) if contact.any() else np.zeros(3), mean_speed=float(np.mean(v[moving] @ d)) if moving.any() else 0.0,
        n_samples=int(v.shape[0]), n_contact_samples=int(contact.sum()), angular_velocity=omega,
        mean_position=where,
    )


def phase_impedances(model, demos, dt: float, *, position_columns=slice(0, 3), force_columns=slice(0, 3),
                     rotation_columns=None, **options) -> list:
    """``derive_impedance`` for every phase of a fitted model.

    Steps are assigned to phases by Viterbi; velocities are finite differences
    of the position columns of the state, forces the force columns, angular
    velocities finite differences of the ``rotation_columns`` (a rotation
    vector; None: the state has no orientation), mean positions the mean of
    the position columns.  A phase with fewer than 2
    steps gets ``None``.  Each phase's ``successor`` is the phase its Viterbi
    paths most often went on to after their last stretch of it (None if none did).
    """
    vel, frc, lab, omg, pos = [], [], [], [], []
    for states, forces in demos:
        states = np.asarray(states, dtype=np.float64)
        forces = np.asarray(forces, dtype=np.float64)
        lab.append(model.viterbi(states, forces))  # (T-1,): one phase per step
        vel.append(np.diff(states[:, position_columns], axis=0) / dt)
        pos.append(states[:-1, position_columns])
        frc.append(forces[:-1, force_columns])
        if rotation_columns is not None:
            omg.append(np.diff(states[:, rotation_columns], axis=0) / dt)
    # the phase each demonstration went on to after its LAST stretch of a phase: a phase
    # flickering with another on its way in (the two-sided valley's plate phase: 8 short
    # returns to free motion against 6 entries into the groove) is not what follows it
    entered = np.zeros((model.n_phases, model.n_phases), dtype=np.int64)
    for path in lab:
        change = np.flatnonzero(np.diff(path))
        last = {}
        for c in change:
            last[int(path[c])] = int(path[c + 1])
        for j, k in last.items():
            entered[j, k] += 1
    lab, vel, frc, pos = np.concatenate(lab), np.vstack(vel), np.vstack(frc), np.vstack(pos)
    omg = np.vstack(omg) if omg else None
    out = []
    for j in range(model.n_phases):
        sel = lab == j
        if sel.sum() < 2:
            out.append(None)
            continue
        try:
            imp = derive_impedance(vel[sel], frc[sel], angular_velocities=None if omg is None else omg[sel],
                                   positions=pos[sel], **options)
            out.append(replace(imp, successor=int(np.argmax(entered[j])) if entered[j].any() else None))
        except ValueError:
            out.append(None)
    return out
