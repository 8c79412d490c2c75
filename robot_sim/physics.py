"""MuJoCo physics of a world with the LWR4+: owns the state, steps at 1 ms.

Model/Data split: ``Simulation.model`` is the immutable MjModel,
``Simulation.data`` the MjData workspace.  Everything is looked up by name
once; the step writes into preallocated buffers (no allocation per step) and
hands out copies.  Step order (dm_control's): ``apply(tau, hand_wrench)`` ->
``step()`` -> read.  A step that produces NaN or a MuJoCo warning raises
``PhysicsError`` instead of carrying garbage on.
"""

from __future__ import annotations

import mujoco
import numpy as np

from robot_sim.worlds import TIMESTEP, WorldSpec

JOINTS = tuple(f"joint{i}" for i in range(1, 8))


class PhysicsError(RuntimeError):
    """The simulation diverged or MuJoCo reported a problem."""


class Simulation:
    def __init__(self, world: WorldSpec):
        self.world = world
        self.model = mujoco.MjModel.from_xml_string(world.xml)
        if abs(self.model.opt.timestep - TIMESTEP) > 1e-12:
            raise ValueError(f"world {world.name}: timestep {self.model.opt.timestep} s, expected {TIMESTEP} s")
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
        self._force_adr = m.sensor_adr[m.sensor("ft_force").id]
        self._torque_adr = m.sensor_adr[m.sensor("ft_torque").id]
        self._role_of_geom = {m.geom(name).id: role for name, role in world.contact_geoms.items()}
        self._qfrc = np.zeros(m.nv)
        self._hand_qfrc = np.zeros(m.nv)
        self._contact6 = np.zeros(6)
        self._wrench = np.zeros(6)

    @property
    def time(self) -> float:
        return float(self.data.time)

    # ----------------------------------------------------------------- state

    def reset(self, q: np.ndarray, qd: np.ndarray | None = None) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self._qpos] = q
        if qd is not None:
            self.data.qvel[self._dof] = qd
        mujoco.mj_forward(self.model, self.data)

    def joint_positions(self, out: np.ndarray | None = None) -> np.ndarray:
        out = np.empty(7) if out is None else out
        np.copyto(out, self.data.qpos[self._qpos])
        return out

    def joint_velocities(self, out: np.ndarray | None = None) -> np.ndarray:
        out = np.empty(7) if out is None else out
        np.copyto(out, self.data.qvel[self._dof])
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
        self._hand_qfrc[:] = 0.0
        if hand_wrench is not None:
            mujoco.mj_applyFT(self.model, self.data, hand_wrench[:3], hand_wrench[3:],
                              self.data.site_xpos[self._flange_site], self._flange_body, self._hand_qfrc)
        np.copyto(self._qfrc, self._hand_qfrc)
        self._qfrc[self._dof] += tau
        self.data.qfrc_applied[:] = self._qfrc

    def step(self) -> None:
        mujoco.mj_step(self.model, self.data)
        if not np.isfinite(self.data.qacc).all() or self.data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number:
            raise PhysicsError(f"simulation diverged at t={self.data.time:.3f} s (bad acceleration)")

    # ------------------------------------------------------------- sensing

    def external_joint_torques(self, out: np.ndarray | None = None) -> np.ndarray:
        """Joint torques from everything outside the arm's drives: contacts (and
        joint-limit constraints) and the hand, as the LWR's joint torque
        sensors see them after its dynamic model is subtracted."""
        out = np.empty(7) if out is None else out
        np.copyto(out, self.data.qfrc_constraint[self._dof])
        out += self._hand_qfrc[self._dof]
        return out

    def sensor_wrench(self, out: np.ndarray | None = None) -> np.ndarray:
        """The wrench the tool transmits to the F/T sensor, in the sensor frame:
        [Fx, Fy, Fz, Tx, Ty, Tz].  At rest it is the tool's weight plus the
        environment's force on the tool (what a real sensor reads before tare).

        MuJoCo's force/torque sensors report the force the child body (tool)
        exerts... with the opposite sign (the parent's reaction); negated here.
        """
        out = np.empty(6) if out is None else out
        out[:3] = self.data.sensordata[self._force_adr:self._force_adr + 3]
        out[3:] = self.data.sensordata[self._torque_adr:self._torque_adr + 3]
        np.negative(out, out=out)
        return out

    def contact_wrench(self) -> tuple[np.ndarray, set]:
        """Total force the environment exerts on the tool tip (world axes) and
        the roles ('plate', 'coupler') of the geoms touched."""
        total = np.zeros(3)
        roles = set()
        d = self.data
        for k in range(d.ncon):
            c = d.contact[k]
            if c.geom1 == self._tip_geom:
                other = c.geom2
            elif c.geom2 == self._tip_geom:
                other = c.geom1
            else:
                continue
            mujoco.mj_contactForce(self.model, d, k, self._contact6)
            # the contact frame's rows are its axes, the first the normal from
            # geom1 to geom2; the force acts on geom2 along it
            f_world = c.frame.reshape(3, 3).T @ self._contact6[:3]
            total += f_world if c.geom2 == self._tip_geom else -f_world
            roles.add(self._role_of_geom.get(other, "other"))
        return total, roles

    def touching(self) -> list[str]:
        """Names of the geoms the tool tip touches."""
        out = []
        for k in range(self.data.ncon):
            c = self.data.contact[k]
            if c.geom1 == self._tip_geom:
                out.append(self.model.geom(c.geom2).name)
            elif c.geom2 == self._tip_geom:
                out.append(self.model.geom(c.geom1).name)
        return out
