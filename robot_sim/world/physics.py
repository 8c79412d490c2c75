"""MuJoCo physics of a world with the LWR4+: owns the state, steps at 1 ms.

Model/Data split: ``Simulation.model`` is the immutable MjModel,
``Simulation.data`` the MjData workspace.  Everything is looked up by name
once; the step writes into preallocated buffers and hands out copies.  Step
order (dm_control's): ``apply(tau, hand_wrench)`` -> ``step()`` -> read.  A
step that produces NaN or a MuJoCo warning raises ``PhysicsError`` instead of
carrying garbage on.

``joint_positions(out)``, ``joint_velocities(out)``, ``apply`` and ``step``
allocate nothing (tests/robot_sim/test_allocation.py): the MjData arrays are
viewed once (MjData never moves them), and the little arithmetic is done by
numba kernels that reach the buffers through their addresses (``kernel_plumbing.addresses``).
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import mujoco
import numpy as np
from numba import njit, types

from kernel_plumbing import blas
from kernel_plumbing.addresses import (JIT, HoldsAddresses, address, addresses, carray_at, entry, int64_address,
                                       int64_array_at)
from robot_sim.world.tasks import TIMESTEP, WorldSpec

JOINTS = tuple(f"joint{i}" for i in range(1, 8))


@njit(**JIT)
def _applied_forces(nv, cdof_at, com_at, point_at, chain_at, wrench_at, hand, tau_at, arm_dof, hand_at, out_at):
    """qfrc_applied = the hand's wrench at the point (mj_applyFT) + tau on the arm's dofs.

    As mj_jac: the dofs of the body's chain move the point with
    jacp = cdof_lin + cdof_ang x (point - subtree_com[root]), jacr = cdof_ang."""
    cdof = carray_at(cdof_at, (nv, 6))
    qfrc_hand = carray_at(hand_at, (nv,))
    out = carray_at(out_at, (nv,))
    if hand:
        com, point = carray_at(com_at, (3,)), carray_at(point_at, (3,))
        chain, w = carray_at(chain_at, (nv,)), carray_at(wrench_at, (6,))
        ox, oy, oz = point[0] - com[0], point[1] - com[1], point[2] - com[2]
        for i in range(nv):
            if chain[i] == 0.0:
                qfrc_hand[i] = 0.0
                continue
            ax, ay, az = cdof[i, 0], cdof[i, 1], cdof[i, 2]
            jx = cdof[i, 3] + ay * oz - az * oy
            jy = cdof[i, 4] + az * ox - ax * oz
            jz = cdof[i, 5] + ax * oy - ay * ox
            qfrc_hand[i] = jx * w[0] + jy * w[1] + jz * w[2] + ax * w[3] + ay * w[4] + az * w[5]
    else:
        qfrc_hand[:] = 0.0
    out[:] = qfrc_hand
    tau = carray_at(tau_at, (7,))
    for i in range(7):
        out[arm_dof + i] += tau[i]


@njit(**JIT)
def _sensed_at(sensordata_at, force_adr, torque_adr, constraint_at, hand_at, nv, arm_dof, wrench_at, torques_at):
    """The F/T sensor's wrench (MuJoCo's reading negated) and the arm's external joint
    torques (constraint forces + the hand's), as the numpy expressions had them."""
    sensordata = carray_at(sensordata_at, (max(force_adr, torque_adr) + 3,))
    constraint, hand = carray_at(constraint_at, (nv,)), carray_at(hand_at, (nv,))
    wrench, torques = carray_at(wrench_at, (6,)), carray_at(torques_at, (7,))
    for i in range(3):
        wrench[i] = -sensordata[force_adr + i]
        wrench[3 + i] = -sensordata[torque_adr + i]
    for i in range(7):
        torques[i] = constraint[arm_dof + i] + hand[arm_dof + i]


@njit(**JIT)
def all_finite_at(addr, n):
    a = carray_at(addr, (n,))
    for i in range(n):
        if not np.isfinite(a[i]):
            return False
    return True


# mj_contactForce(const mjModel*, const mjData*, int id, mjtNum result[6])
_call_contact_force = blas.foreign(types.void, types.int64, types.int64, types.int32, types.int64)


@njit(**JIT)
def _tip_contacts_at(ncon, contact_at, stride, geom1_off, geom2_off, frame_off, tip, contact_force_fn, model_at,
                     data_at, gemv_fn, force6_at, force_at, total_at, others_at, max_others):
    """``Simulation.contacts``'s loop over MuJoCo's contact array, reading the mjContact
    structs where MuJoCo keeps them: the total force on the tip (world axes) into
    ``total``, the other geoms' ids into ``others``; returns how many contacts touch the
    tip.  Each contact's force through MuJoCo's own ``mj_contactForce``, its rotation to
    world axes through the dgemv numpy's ``frame.reshape(3, 3).T @ f`` calls (row-major,
    transposed, lda 3), the sum in the same order: the Python loop's bits."""
    total = carray_at(total_at, (3,))
    force = carray_at(force_at, (3,))
    others = carray_at(others_at, (max_others,))
    total[:] = 0.0
    count = 0
    for k in range(ncon):
        record = contact_at + k * stride
        g1, g2 = blas.int32_at(record + geom1_off), blas.int32_at(record + geom2_off)
        if g1 == tip:
            other = g2
        elif g2 == tip:
            other = g1
        else:
            continue
        _call_contact_force(contact_force_fn, model_at, data_at, np.int32(k), force6_at)
        blas.call_gemv(gemv_fn, np.int32(blas.ROW_MAJOR), np.int32(blas.TRANS), 3, 3, 1.0, record + frame_off, 3,
                       force6_at, 1, 0.0, force_at, 1)
        if g2 == tip:
            for i in range(3):
                total[i] += force[i]
        else:
            for i in range(3):
                total[i] -= force[i]
        if count < max_others:
            others[count] = other
        count += 1
    return count


def _mujoco_function(name: str) -> tuple[int, str]:
    """The address of a function of MuJoCo's C library as the bindings loaded it (0 and
    why not): the file mapped from beside the ``mujoco`` package in this process."""
    here = Path(mujoco.__file__).resolve().parent
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError as e:  # not Linux
        return 0, f"cannot see which libraries this process loaded ({e})"
    for line in maps.splitlines():
        path = Path(line.split(maxsplit=5)[-1])
        if path.parent == here and path.name.startswith("libmujoco.so"):
            try:
                return ctypes.cast(getattr(ctypes.CDLL(str(path)), name), ctypes.c_void_p).value or 0, ""
            except (OSError, AttributeError) as e:
                return 0, f"{path.name}: {e}"
    return 0, f"MuJoCo's library is not mapped from {here} in this process"


_CONTACT_FORCE, WHY_NO_CONTACT_KERNEL = _mujoco_function("mj_contactForce")
# mj_step(const mjModel*, mjData*): the step from a kernel (bit for bit the bindings' step)
MJ_STEP, WHY_NO_STEP_KERNEL = _mujoco_function("mj_step")
_call_step = blas.foreign(types.void, types.int64, types.int64)
if _CONTACT_FORCE and not blas.AVAILABLE:
    _CONTACT_FORCE, WHY_NO_CONTACT_KERNEL = 0, blas.WHY
# The addresses a step kernel reaches (``Simulation.table``), by index
STEP_BUFFERS = ("cdof", "com", "flange", "chain", "wrench", "tau", "hand", "applied", "qacc", "model", "data",
                "bad_qacc")
_CDOF, _COM, _FLANGE, _CHAIN, _WRENCH, _TAU, _HAND, _APPLIED, _QACC, _MODEL, _DATA, _BAD_QACC = range(len(STEP_BUFFERS))


@njit(**JIT)
def step_at(table_at, nv, arm_dof, hand, step_fn):
    """``Simulation.apply`` (tau and the hand's wrench already in their buffers; ``hand``:
    the hand acts) and ``Simulation.step`` through MuJoCo's C function at ``step_fn``.
    False: the step diverged (a non-finite acceleration, or MuJoCo's bad-acceleration
    warning), as ``step`` raises PhysicsError."""
    at = int64_array_at(table_at, len(STEP_BUFFERS))
    _applied_forces(nv, at[_CDOF], at[_COM], at[_FLANGE], at[_CHAIN], at[_WRENCH], hand, at[_TAU], arm_dof,
                    at[_HAND], at[_APPLIED])
    _call_step(step_fn, at[_MODEL], at[_DATA])
    return all_finite_at(at[_QACC], nv) and blas.int32_at(at[_BAD_QACC]) == 0


# the geom ids of the contacts on the tip a kernel call can report; more go the Python way
_MAX_TIP_CONTACTS = 64
_TOUCHED_KEPT = 256  # sets of geoms whose names are kept (a world has a few the tip meets)

_apply_forces = entry(_applied_forces, f"{addresses(6)}, boolean, {addresses(4)}")
_sensed = entry(_sensed_at, addresses(9))
all_finite = entry(all_finite_at, addresses(2))
_tip_contacts = entry(_tip_contacts_at, addresses(16)) if _CONTACT_FORCE else None


class PhysicsError(RuntimeError):
    """The simulation diverged or MuJoCo reported a problem."""


class Simulation(HoldsAddresses):
    def __init__(self, world: WorldSpec):
        self.world = world
        self.model = mujoco.MjModel.from_xml_string(world.xml)
        step = self.model.opt.timestep
        if not (step > 0 and abs(TIMESTEP / step - round(TIMESTEP / step)) < 1e-9):
            raise ValueError(f"world {world.name}: timestep {step} s, expected {TIMESTEP} s or a whole fraction of it")
        self.substeps = round(TIMESTEP / step)  # physics steps per 1 ms (FRI_CYCLE_NS)
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._qpos = np.array([m.jnt_qposadr[m.joint(n).id] for n in JOINTS])
        self._dof = np.array([m.jnt_dofadr[m.joint(n).id] for n in JOINTS])
        self._flange_body = m.body("link7").id
        self._tool_body = m.body("tool").id
        self._tcp_site = m.site("tcp").id
        self._ft_site = m.site("ft_site").id
        self._flange_site = m.site("flange").id
        self._tip_geom = m.geom("tool_tip").id
        self._force_adr = int(m.sensor_adr[m.sensor("ft_force").id])
        self._torque_adr = int(m.sensor_adr[m.sensor("ft_torque").id])
        self._role_of_geom = {m.geom(name).id: role for name, role in world.contact_geoms.items()}
        self._geom_names = [m.geom(i).name for i in range(m.ngeom)]
        self._hand_qfrc = np.zeros(m.nv)
        self._contact6 = np.zeros(6)
        # the contact kernel's buffers, and where MuJoCo keeps the contacts (found at the
        # first contact: d->contact is the arena's start, for the life of the MjData)
        self._contact_force3 = np.zeros(3)
        self._contact_total = np.zeros(3)
        self._tip_others = np.zeros(_MAX_TIP_CONTACTS)
        self._contact_layout: tuple[int, ...] | None = None
        self._contact_args: tuple | None = None
        self._touched: dict[bytes, tuple[frozenset, tuple]] = {}  # the kernel's geom ids -> (roles, names)
        self._tau = np.zeros(7)
        self._hand_wrench = np.zeros(6)
        # the per-step arrays, viewed once: each index or slice would make a new array
        d = self.data
        a, v = int(self._qpos[0]), int(self._dof[0])
        if not (np.array_equal(self._qpos, np.arange(a, a + 7)) and np.array_equal(self._dof, np.arange(v, v + 7))):
            raise ValueError(f"world {world.name}: the arm's joints must be consecutive in qpos and qvel")
        self._arm_qpos = d.qpos[a:a + 7]
        self._arm_qvel = d.qvel[v:v + 7]
        self._arm_dof = v
        self._nv = m.nv
        self._bad_qacc = d.warning[mujoco.mjtWarning.mjWARN_BADQACC]  # a live view of the counter
        # the dofs that move the flange: mj_jac's chain, as a mask
        chain = np.zeros(m.nv)
        body = self._flange_body
        while body and not m.body_dofnum[body]:
            body = m.body_parentid[body]
        dof = m.body_dofadr[body] + m.body_dofnum[body] - 1 if body else -1
        while dof >= 0:
            chain[dof] = 1.0
            dof = m.dof_parentid[dof]
        self._chain = chain
        self._at = {"cdof": address(d.cdof), "com": address(d.subtree_com[m.body_rootid[self._flange_body]]),
                    "flange": address(d.site_xpos[self._flange_site]), "chain": address(chain),
                    "wrench": address(self._hand_wrench), "tau": address(self._tau), "hand": address(self._hand_qfrc),
                    "applied": address(d.qfrc_applied), "qacc": address(d.qacc),
                    "sensordata": address(d.sensordata), "constraint": address(d.qfrc_constraint),
                    "model": m._address, "data": d._address, "contact6": address(self._contact6),
                    "force3": address(self._contact_force3), "total": address(self._contact_total),
                    "others": address(self._tip_others),
                    # the bad-acceleration warning's counter, which step_at reads as step() does
                    "bad_qacc": d.warning.number.ctypes.data
                    + d.warning.number.strides[0] * mujoco.mjtWarning.mjWARN_BADQACC}
        # the step kernel's addresses (step_at), and what it is called with besides
        self._table = np.array([self._at[name] for name in STEP_BUFFERS], dtype=np.int64)
        self.table_at = int64_address(self._table)
        self.arm_qpos_at, self.arm_qvel_at = address(self._arm_qpos), address(self._arm_qvel)
        self.tau_at, self.nv, self.arm_dof = self._at["tau"], self._nv, self._arm_dof
        self._sense_args = (self._at["sensordata"], self._force_adr, self._torque_adr, self._at["constraint"],
                            self._at["hand"], self._nv, self._arm_dof)  # sense_at's, but for the outputs

    @property
    def time(self) -> float:
        return float(self.data.time)

    # ----------------------------------------------------------------- state

    def reset(self, q: np.ndarray, qd: np.ndarray | None = None) -> None:
        mujoco.mj_resetData(self.model, self.data)
        # the last episode's hand must not linger in the external torques the KRC
        # estimates its force from (it latched a force-limit stop at the next start)
        self._hand_qfrc[:] = 0.0
        self.data.qpos[self._qpos] = q
        if qd is not None:
            self.data.qvel[self._dof] = qd
        mujoco.mj_forward(self.model, self.data)

    def joint_positions(self, out: np.ndarray | None = None) -> np.ndarray:
        if out is None:
            return self._arm_qpos.copy()
        out[...] = self._arm_qpos
        return out

    def joint_velocities(self, out: np.ndarray | None = None) -> np.ndarray:
        if out is None:
            return self._arm_qvel.copy()
        out[...] = self._arm_qvel
        return out

    def tcp_position(self) -> np.ndarray:
        return self.data.site_xpos[self._tcp_site].copy()

    def tcp_rotation(self) -> np.ndarray:
        return self.data.site_xmat[self._tcp_site].reshape(3, 3).copy()

    # ---------------------------------------------------------------- step

    def apply(self, tau: np.ndarray, hand_wrench: np.ndarray | None = None) -> None:
        """Joint torques (7,) and the teacher's hand wrench (6,) [force; torque]
        in world axes, applied at the flange (above the F/T sensor, where a
        person grasps the arm, so the sensor sees contact and tool, not the hand)."""
        # the hand acts through the Jacobian at the flange of the last computed
        # kinematics, as mj_applyFT would (its bindings allocate per call)
        self._tau[...] = tau
        hand = hand_wrench is not None
        if hand:
            self._hand_wrench[...] = hand_wrench
        at = self._at
        _apply_forces(self._nv, at["cdof"], at["com"], at["flange"], at["chain"], at["wrench"], hand,
                      at["tau"], self._arm_dof, at["hand"], at["applied"])

    def load_hand(self, hand_wrench: np.ndarray) -> None:
        """The hand's wrench for ``step_at`` (as ``apply`` takes it)."""
        self._hand_wrench[...] = hand_wrench

    def step(self) -> None:
        mujoco.mj_step(self.model, self.data)
        if not all_finite(self._at["qacc"], self._nv) or self._bad_qacc.number:
            raise PhysicsError(f"simulation diverged at t={self.data.time:.3f} s (bad acceleration)")

    # ------------------------------------------------------------- sensing

    def external_joint_torques(self, out: np.ndarray | None = None) -> np.ndarray:
        """Joint torques from everything outside the arm's drives: contacts (and
        joint-limit constraints) and the hand, as the LWR's joint torque
        sensors see them after its dynamic model is subtracted."""
        out = np.empty(7) if out is None else out
        self.sense(np.empty(6), out)
        return out

    def sensor_wrench(self, out: np.ndarray | None = None) -> np.ndarray:
        """The wrench the tool transmits to the F/T sensor, in the sensor frame:
        [Fx, Fy, Fz, Tx, Ty, Tz].  At rest it is the tool's weight plus the
        environment's force on the tool (what a real sensor reads before tare).

        MuJoCo's force/torque sensors report the force the child body (tool)
        exerts... with the opposite sign (the parent's reaction); negated here.
        """
        out = np.empty(6) if out is None else out
        self.sense(out, np.empty(7))
        return out

    def sense(self, wrench: np.ndarray, torques: np.ndarray) -> None:
        """``sensor_wrench`` into ``wrench`` (6,) and ``external_joint_torques`` into
        ``torques`` (7,) in one kernel call (contiguous float64 buffers; the kernel writes
        by address, so the shapes are checked here)."""
        if np.shape(wrench) != (6,) or np.shape(torques) != (7,):
            raise ValueError(f"sense: wrench (6,) and torques (7,), got {np.shape(wrench)} and {np.shape(torques)}")
        self.sense_at(address(wrench), address(torques))

    def sense_at(self, wrench_at: int, torques_at: int) -> None:
        """``sense`` into the buffers at these addresses (kernel_plumbing.addresses): the cell's,
        every cycle."""
        _sensed(*self._sense_args, wrench_at, torques_at)

    def contacts(self) -> tuple[np.ndarray, set, list[str]]:
        """What the tool tip touches, read once: the total force the environment
        exerts on it (world axes), the roles ('plate', 'coupler') of the geoms
        touched and their names.  One kernel call over MuJoCo's contact array where
        MuJoCo's library and numpy's BLAS can be called from one (``contacts_numpy``
        otherwise: the same numbers)."""
        touched = self._tip_touches()
        if touched is None:
            return self.contacts_numpy()
        roles, names = touched
        return self._contact_total.copy(), set(roles), list(names)

    def tip_contacts(self) -> tuple[np.ndarray, list[str]]:
        """``contacts`` without the roles (the cell's, every step): the force and the names."""
        touched = self._tip_touches()
        if touched is None:
            total, _, names = self.contacts_numpy()
            return total, names
        return self._contact_total.copy(), list(touched[1])

    def _tip_touches(self) -> tuple[frozenset, tuple] | None:
        """The kernel's pass over the contacts: the total force in ``_contact_total``, and the
        roles and names of the geoms the tip touches (None: no contact, or no kernel, or more
        than it keeps: ``contacts_numpy``'s to say).  The names of a set of geoms are made
        once: from one step to the next the tip mostly touches what it touched."""
        n = self.data.ncon
        if n == 0 or _tip_contacts is None:
            return None
        count = _tip_contacts(n, *(self._contact_args or self._locate_contacts()))
        if count > _MAX_TIP_CONTACTS:
            return None
        key = self._tip_others[:count].tobytes()
        touched = self._touched.get(key)
        if touched is None:
            others = [int(g) for g in self._tip_others[:count].tolist()]
            touched = (frozenset(self._role_of_geom.get(g, "other") for g in others),
                       tuple(self._geom_names[g] for g in others))
            if len(self._touched) < _TOUCHED_KEPT:
                self._touched[key] = touched
        return touched

    def _locate_contacts(self) -> tuple[int, ...]:
        """Where the contact array is and where an mjContact keeps the fields the kernel
        reads, from the bindings' views of the first contact (there must be one); with the
        rest of the kernel's arguments after the contact count, gathered once."""
        c = self.data.contact
        start = c.dist.__array_interface__["data"][0]  # dist: the struct's first field
        self._contact_layout = (start, c.geom1.strides[0], c.geom1.__array_interface__["data"][0] - start,
                                c.geom2.__array_interface__["data"][0] - start,
                                c.frame.__array_interface__["data"][0] - start)
        at = self._at
        self._contact_args = (*self._contact_layout, self._tip_geom, _CONTACT_FORCE, at["model"], at["data"],
                              blas.GEMV, at["contact6"], at["force3"], at["total"], at["others"], _MAX_TIP_CONTACTS)
        return self._contact_args

    def contacts_numpy(self) -> tuple[np.ndarray, set, list[str]]:
        """``contacts`` through the bindings and numpy, contact by contact."""
        total = np.zeros(3)
        roles = set()
        names = []
        d = self.data
        n = d.ncon
        if n == 0:
            return total, roles, names
        contact = d.contact
        # the contact list's fields as arrays: one wrapper object per contact cost more than the rest
        geom1, geom2, frames = contact.geom1.tolist(), contact.geom2.tolist(), contact.frame
        tip = self._tip_geom
        for k in range(n):
            g1, g2 = geom1[k], geom2[k]
            if g1 == tip:
                other = g2
            elif g2 == tip:
                other = g1
            else:
                continue
            mujoco.mj_contactForce(self.model, d, k, self._contact6)
            # the contact frame's rows are its axes, the first the normal from
            # geom1 to geom2; the force acts on geom2 along it
            f_world = frames[k].reshape(3, 3).T @ self._contact6[:3]
            total += f_world if g2 == tip else -f_world
            roles.add(self._role_of_geom.get(other, "other"))
            names.append(self._geom_names[other])
        return total, roles, names

    def contact_wrench(self) -> tuple[np.ndarray, set]:
        """Total force the environment exerts on the tool tip (world axes) and
        the roles ('plate', 'coupler') of the geoms touched."""
        total, roles, _ = self.contacts()
        return total, roles

    def touching(self) -> list[str]:
        """Names of the geoms the tool tip touches."""
        return self.contacts()[2]
