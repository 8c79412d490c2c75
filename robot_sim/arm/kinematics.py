"""The KRC's own model of the arm: Pinocchio Model/Data built from the URDF.

Frames are named in the arguments and results: ``oMtcp`` is the pose of the tcp
frame in the base (world) frame; Jacobians are taken in
``LOCAL_WORLD_ALIGNED`` (origin at the frame, axes of the base) unless stated.
Results are copies, except what ``views`` and ``frame_views`` hand out.

The realtime step (robot_sim.krc.law) must not allocate, and every Pinocchio
function that returns an array returns a new one, as does every access to an
attribute of ``data``.  For it, ``update_dynamics`` runs algorithms that only
fill ``data`` in place, and ``views``/``frame_views`` hand out views of
``data``'s buffers, taken once: Pinocchio writes into the same memory on every
update, so they stay current (and valid as long as this object lives).
"""

from __future__ import annotations

import logging
import os

import numpy as np
import pinocchio as pin
from numba import types

from kernel_plumbing.blas import foreign
from robot_sim.arm.description import ArmDescription, LWR4

log = logging.getLogger(__name__)


def _load_pinocchio_inplace():
    """(the compiled robot_sim.arm._pinocchio_inplace module or None, why not).

    Imported after pinocchio: its libraries are then loaded and resolve the
    extension's.  A module built against another Pinocchio would read Model and
    Data with the wrong layout, so a version mismatch counts as missing.
    ROBOT_SIM_PINOCCHIO_INPLACE=0 turns it off, to compare with the bindings."""
    if os.environ.get("ROBOT_SIM_PINOCCHIO_INPLACE", "1") == "0":
        return None, "turned off by ROBOT_SIM_PINOCCHIO_INPLACE=0"
    try:
        from robot_sim.arm import _pinocchio_inplace as native
    except ImportError as e:
        return None, f"robot_sim.arm._pinocchio_inplace did not import ({e}); reinstall with a C++ compiler"
    if native.PINOCCHIO_VERSION != pin.__version__:
        return None, (f"robot_sim.arm._pinocchio_inplace was built against Pinocchio {native.PINOCCHIO_VERSION}, "
                      f"{pin.__version__} is loaded; reinstall the project")
    return native, None


PINOCCHIO_INPLACE, PINOCCHIO_INPLACE_MISSING = _load_pinocchio_inplace()
# an extension built before it had this function (an older install) is still used for the rest
_MEASURED_KINEMATICS = getattr(PINOCCHIO_INPLACE, "measured_kinematics", None)
# the same two updates as C functions, for the cell's compiled cycle (0: an extension without them):
# int (model, data, q, v) and int (model, data, q, frame, J), every argument an address
COMPUTE_ALL_TERMS = getattr(PINOCCHIO_INPLACE, "COMPUTE_ALL_TERMS", 0)
MEASURED_KINEMATICS = getattr(PINOCCHIO_INPLACE, "MEASURED_KINEMATICS", 0)
# int (R, out): pinocchio.log3 of 9 row-major numbers into 3, the bindings' bits
LOG3 = getattr(PINOCCHIO_INPLACE, "LOG3", 0)
# in a kernel: call_compute_all_terms(COMPUTE_ALL_TERMS, model, data, q, v) -> 0 on success
call_compute_all_terms = foreign(types.int32, types.int64, types.int64, types.int64, types.int64)
call_measured_kinematics = foreign(types.int32, types.int64, types.int64, types.int64, types.int64, types.int64)
call_log3 = foreign(types.int32, types.int64, types.int64)

FRAMES = ("flange", "ati_sensor", "tool", "tcp")

# elbow up, tool pointing down, tcp about 0.6 m in front of the base at table height
READY = np.array([0.0, -0.5, 0.0, 1.5, 0.0, -1.1, 0.0])


class ArmKinematics:
    """Forward kinematics, Jacobians, dynamics terms and IK of the LWR4+."""

    _warned_inplace_missing = False

    def __init__(self, description: ArmDescription = LWR4):
        self.description = description
        self.model = pin.buildModelFromXML(description.to_urdf())
        self.data = self.model.createData()
        if PINOCCHIO_INPLACE is None and not ArmKinematics._warned_inplace_missing:
            ArmKinematics._warned_inplace_missing = True
            log.warning("the control step allocates 2 x 56 B per cycle: %s", PINOCCHIO_INPLACE_MISSING)
        if self.model.nq != description.n_joints:
            raise ValueError(f"URDF gave {self.model.nq} joints, expected {description.n_joints}")
        self.frame_ids = {name: self.model.getFrameId(name) for name in FRAMES}
        self.q_min = np.array(description.q_min)
        self.q_max = np.array(description.q_max)
        d = self.data
        # the buffers update_dynamics fills: joint Jacobians (6, nv) in the world
        # frame [linear; angular] (about the world origin), the joint-space
        # inertia (nv, nv; its upper triangle is what the CRBA guarantees), and
        # the nonlinear effects (nv,)
        self.views = {"J": d.J, "M": d.M, "nle": d.nle}
        # where the C++ Model and Data are, for COMPUTE_ALL_TERMS and MEASURED_KINEMATICS ((0, 0): not here)
        self.native = PINOCCHIO_INPLACE.model_and_data(self.model, self.data) if COMPUTE_ALL_TERMS else (0, 0)
        self._frame_views = {name: (d.oMf[fid].rotation, d.oMf[fid].translation)
                             for name, fid in self.frame_ids.items()}

    def update(self, q: np.ndarray, qd: np.ndarray | None = None) -> None:
        """Kinematics (and Jacobians) at q; call before the frame queries below."""
        if qd is None:
            pin.forwardKinematics(self.model, self.data, q)
        else:
            pin.forwardKinematics(self.model, self.data, q, qd)
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)

    def update_with_jacobian(self, q: np.ndarray, frame: str, out: np.ndarray) -> None:
        """``update(q)``, then the frame's Jacobian in its own axes (LOCAL) into ``out``, a
        C-contiguous (6, nv) float64 array: what a cycle's measurement needs, in one call
        to robot_sim.arm._pinocchio_inplace where it has it (the same algorithms, the same bits;
        the bindings copy q into each of their three calls and return a new array)."""
        if _MEASURED_KINEMATICS is not None:
            _MEASURED_KINEMATICS(self.model, self.data, q, self.frame_ids[frame], out.T)
        else:
            self.update(q)
            np.copyto(out, pin.getFrameJacobian(self.model, self.data, self.frame_ids[frame], pin.ReferenceFrame.LOCAL))

    def update_frames(self, q: np.ndarray) -> None:
        """Only the frame placements at q (no Jacobians): what drawing the arm needs."""
        pin.framesForwardKinematics(self.model, self.data, q)

    def update_dynamics(self, q: np.ndarray, qd: np.ndarray) -> None:
        """``update(q, qd)`` plus the joint-space inertia and the nonlinear
        effects, into ``views`` and ``frame_views``.  No Python object or numpy
        array is allocated (computeJointJacobians and nonLinearEffects would
        return copies), and with robot_sim.arm._pinocchio_inplace no C++ heap block
        either: Pinocchio's own bindings copy q and qd into two new Eigen
        vectors, which is the fallback when the extension is missing."""
        if PINOCCHIO_INPLACE is not None:
            PINOCCHIO_INPLACE.compute_all_terms(self.model, self.data, q, qd)
        else:
            pin.computeAllTerms(self.model, self.data, q, qd)
            pin.updateFramePlacements(self.model, self.data)

    def frame_views(self, frame: str = "tcp") -> tuple[np.ndarray, np.ndarray]:
        """(rotation (3, 3), translation (3,)) of oMframe: live views of ``data``."""
        return self._frame_views[frame]

    def support(self, frame: str = "tcp") -> np.ndarray:
        """(nv,) 1.0 for the velocities that move the frame, 0.0 for the others:
        the columns of the joint Jacobians that make up the frame's."""
        mask = np.zeros(self.model.nv)
        for j in self.model.supports[self.model.frames[self.frame_ids[frame]].parentJoint]:
            if j > 0:
                joint = self.model.joints[j]
                mask[joint.idx_v:joint.idx_v + joint.nv] = 1.0
        return mask

    def placement(self, frame: str = "tcp") -> pin.SE3:
        """oMframe after ``update`` (a copy)."""
        return pin.SE3(self.data.oMf[self.frame_ids[frame]])

    def jacobian(self, frame: str = "tcp", reference=pin.ReferenceFrame.LOCAL_WORLD_ALIGNED) -> np.ndarray:
        """(6, 7) frame Jacobian [linear; angular] after ``update``."""
        return pin.getFrameJacobian(self.model, self.data, self.frame_ids[frame], reference).copy()

    def forward(self, q: np.ndarray, frame: str = "tcp") -> pin.SE3:
        pin.framesForwardKinematics(self.model, self.data, q)
        return pin.SE3(self.data.oMf[self.frame_ids[frame]])

    def nonlinear_effects(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Gravity + Coriolis/centrifugal torques: what f_dynamics compensates (eq. 79)."""
        return pin.nonLinearEffects(self.model, self.data, q, qd).copy()

    def gravity(self, q: np.ndarray) -> np.ndarray:
        return pin.computeGeneralizedGravity(self.model, self.data, q).copy()

    def cartesian_mass(self, q: np.ndarray, frame: str = "tcp") -> np.ndarray:
        """(6, 6) operational-space inertia Lambda = (J M^-1 J^T)^-1 at the frame."""
        Minv = pin.computeMinverse(self.model, self.data, q)
        Minv = np.triu(Minv) + np.triu(Minv, 1).T
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        J = self.jacobian(frame)
        return np.linalg.inv(J @ Minv @ J.T + 1e-9 * np.eye(6))

    def inverse_kinematics(self, oMdes: pin.SE3, q0: np.ndarray, frame: str = "tcp", *,
                           tol: float = 1e-6, max_iter: int = 500, damping: float = 1e-6) -> np.ndarray:
        """Joint positions reaching ``oMdes`` from ``q0`` (damped least squares,
        clamped to 0.98 of the joint limits).  Raises ValueError if unreachable."""
        q = np.array(q0, dtype=np.float64)
        posture = q.copy()
        fid = self.frame_ids[frame]
        lo, hi = 0.98 * self.q_min, 0.98 * self.q_max
        err = None
        for _ in range(max_iter):
            pin.framesForwardKinematics(self.model, self.data, q)
            iMd = self.data.oMf[fid].actInv(oMdes)
            err = pin.log(iMd).vector
            if np.linalg.norm(err) < tol:
                return q
            pin.computeJointJacobians(self.model, self.data, q)
            J = pin.getFrameJacobian(self.model, self.data, fid, pin.ReferenceFrame.LOCAL)
            J = -pin.Jlog6(iMd.inverse()) @ J
            Jpinv = J.T @ np.linalg.inv(J @ J.T + damping * np.eye(6))
            # the seven-joint arm is redundant: stay near the seed posture in the null space
            # (faded out near the goal so it cannot hold the iteration off it)
            gain = 0.1 * min(1.0, 100.0 * float(np.linalg.norm(err)))
            v = -Jpinv @ err + gain * (np.eye(7) - Jpinv @ J) @ (posture - q)
            q = np.clip(pin.integrate(self.model, q, 0.5 * v), lo, hi)
        raise ValueError(f"inverse kinematics did not converge: residual {np.linalg.norm(err):.3g} "
                         f"for target {oMdes.translation.tolist()}")
