"""MJCF (MuJoCo) and URDF (Pinocchio), generated from one description, agree."""

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from robot_sim.arm.kinematics import ArmKinematics
from robot_sim.arm.description import LWR4
from robot_sim.world.physics import Simulation
from robot_sim.world.tasks import free_space, hose_coupler, valley


@pytest.fixture(scope="module")
def pair():
    return Simulation(free_space()), ArmKinematics()


def random_configurations(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(np.array(LWR4.q_min) * 0.95, np.array(LWR4.q_max) * 0.95, size=(n, 7))


def test_forward_kinematics_and_jacobians_agree(pair):
    sim, kin = pair
    m, d = sim.model, sim.data
    for q in random_configurations(50):
        sim.reset(q)
        kin.update(q)
        for site, frame in (("tcp", "tcp"), ("flange", "flange"), ("ft_site", "ati_sensor")):
            sid = m.site(site).id
            oM = kin.placement(frame)
            np.testing.assert_allclose(d.site_xpos[sid], oM.translation, atol=1e-10)
            np.testing.assert_allclose(d.site_xmat[sid].reshape(3, 3), oM.rotation, atol=1e-10)
            jacp = np.zeros((3, m.nv))
            jacr = np.zeros((3, m.nv))
            mujoco.mj_jacSite(m, d, jacp, jacr, sid)
            J = kin.jacobian(frame, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
            np.testing.assert_allclose(jacp, J[:3], atol=1e-10)
            np.testing.assert_allclose(jacr, J[3:], atol=1e-10)


def test_gravity_and_inertia_agree(pair):
    sim, kin = pair
    m, d = sim.model, sim.data
    for q in random_configurations(20, seed=1):
        sim.reset(q)  # qvel = 0: qfrc_bias is gravity only
        np.testing.assert_allclose(d.qfrc_bias, kin.gravity(q), atol=1e-9)
        M = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, M)
        M_pin = pin.crba(kin.model, kin.data, q)
        M_pin = np.triu(M_pin) + np.triu(M_pin, 1).T
        # MuJoCo adds the drives' reflected rotor inertia (armature), unknown to the KRC's model
        np.testing.assert_allclose(M - LWR4.armature * np.eye(7), M_pin, atol=1e-9)


def test_description_facts():
    assert sum(link.mass for link in LWR4.links) == pytest.approx(14.4)
    np.testing.assert_allclose(np.rad2deg(LWR4.q_max), [170, 120, 170, 120, 170, 120, 170])
    kin = ArmKinematics()
    stretched = kin.forward(np.zeros(7), "flange")
    # straight up: base-to-flange is the sum of the DH offsets
    np.testing.assert_allclose(stretched.translation, [0, 0, sum(LWR4.d)], atol=1e-12)
    tcp = kin.forward(np.zeros(7), "tcp")
    assert tcp.translation[2] == pytest.approx(sum(LWR4.d) + LWR4.tool.sensor_height + LWR4.tool.sensor_to_tcp)


def test_every_world_loads_with_a_1ms_step():
    for world in (free_space(), valley(), hose_coupler()):
        sim = Simulation(world)
        assert sim.model.opt.timestep == 0.001
        assert sim.model.nq == 7
