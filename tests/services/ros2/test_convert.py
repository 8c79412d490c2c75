"""The run's messages as ROS 2 messages (services.ros2.convert), on hand-made messages:
what each topic carries, at which cycles, in which frame; the /tf tree composes to the
arm's own forward kinematics (Pinocchio), and /robot_description is the URDF the viewer
draws with every geom of the physics' world."""

import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin
import pytest

from robot_sim.arm.kinematics import ArmKinematics
from robot_sim.world.geometry import world_geoms
from services.ros2.convert import JOINT_NAMES, TF_PARENTS, Ros2Rates, RosView
from services.ros2.types import BY_NAME, from_cdr, to_cdr

Q = np.array([0.1, -0.5, 0.2, 1.3, -0.1, 0.6, 0.3])


def state(seq: int, q=Q) -> dict:
    tcp = ArmKinematics().forward(np.asarray(q, dtype=np.float64), "tcp")
    pose = np.hstack([tcp.rotation, tcp.translation[:, None]]).ravel()
    return {"seq": seq, "stamp_ns": seq * 1_000_000, "msr_jnt_pos": list(q), "msr_cart_pos": list(pose)}


@pytest.fixture(scope="module")
def view():
    return RosView("valley")


def test_a_state_gives_the_clock_every_cycle_and_the_arm_every_tenth(view):
    topics = [[t for t, _ in view.take("robot/state", state(seq))] for seq in range(20, 31)]
    assert topics[0] == ["/clock", "/joint_states", "/tf", "/tcp_pose"] == topics[10]
    assert all(t == ["/clock"] for t in topics[1:10])
    slow = RosView("valley", Ros2Rates(state_rate_hz=50, clock_rate_hz=500))
    assert [t for t, _ in slow.take("robot/state", state(21))] == []
    assert [t for t, _ in slow.take("robot/state", state(22))] == ["/clock"]
    assert [t for t, _ in slow.take("robot/state", state(40))] == ["/clock", "/joint_states", "/tf", "/tcp_pose"]


def test_joint_states_and_the_tcp_pose_carry_the_measurement_in_simulated_time(view):
    out = dict(view.take("robot/state", state(1230)))
    js = out["/joint_states"]
    assert list(js.name) == list(JOINT_NAMES) and np.array_equal(js.position, Q)
    assert (js.header.stamp.sec, js.header.stamp.nanosec) == (1, 230_000_000)
    assert (out["/clock"].clock.sec, out["/clock"].clock.nanosec) == (1, 230_000_000)
    pose = out["/tcp_pose"]
    assert pose.header.frame_id == "base"
    tcp = ArmKinematics().forward(Q, "tcp")
    p = pose.pose.position
    assert np.allclose([p.x, p.y, p.z], tcp.translation, atol=1e-12)
    o = pose.pose.orientation
    assert np.allclose(pin.Quaternion(o.w, o.x, o.y, o.z).toRotationMatrix(), tcp.rotation, atol=1e-12)


def test_the_tf_tree_is_the_urdfs_and_composes_to_the_arms_kinematics(view):
    tf = dict(view.take("robot/state", state(0)))["/tf"]
    edges = {t.child_frame_id: t.header.frame_id for t in tf.transforms}
    assert edges == TF_PARENTS
    robot = ET.fromstring(view.description().data)
    assert {j.find("child").get("link"): j.find("parent").get("link") for j in robot.iter("joint")} == TF_PARENTS
    placements = {"base": pin.SE3.Identity()}
    for t in tf.transforms:  # parents come first
        r, v = t.transform.rotation, t.transform.translation
        local = pin.SE3(pin.Quaternion(r.w, r.x, r.y, r.z).toRotationMatrix(), np.array([v.x, v.y, v.z]))
        placements[t.child_frame_id] = placements[t.header.frame_id] * local
    kin = ArmKinematics()
    kin.update_frames(Q)
    for frame in ("link4", "ati_sensor", "tcp"):
        want = kin.data.oMf[kin.model.getFrameId(frame)]
        assert np.allclose(placements[frame].homogeneous, want.homogeneous, atol=1e-12), frame


def test_the_description_draws_every_geom_of_the_world_on_its_link(view):
    robot = ET.fromstring(view.description().data)
    visuals = [(link.get("name"), v) for link in robot.iter("link") for v in link.iter("visual")]
    geoms = world_geoms("valley")
    assert len(visuals) == len(geoms) > 7
    assert [name for name, _ in visuals if name == "base"] == ["base"] * sum(g.frame == "base" for g in geoms)
    boxes = [v.find("geometry/box").get("size") for _, v in visuals if v.find("geometry/box") is not None]
    assert any(size.startswith("0.46 ") for size in boxes)  # the valley's plates, 0.46 m along x
    # the KRC's model is the one Pinocchio reads: visuals do not change it
    assert pin.buildModelFromXML(view.description().data).nq == 7


def test_the_wrench_is_in_the_sensors_frame_and_the_phase_keeps_its_posterior(view):
    wrench = {"seq": 7, "stamp_ns": 7_000_000, "wrench": [1.0, -2.0, 3.5, 0.1, 0.2, -0.3]}
    (topic, ws), = view.take("ft/wrench", wrench)
    assert topic == "/ft_sensor/wrench" and ws.header.frame_id == "ati_sensor"
    assert [ws.wrench.force.x, ws.wrench.force.y, ws.wrench.force.z] == [1.0, -2.0, 3.5]
    assert [ws.wrench.torque.x, ws.wrench.torque.y, ws.wrench.torque.z] == [0.1, 0.2, -0.3]
    every_other = RosView("valley", Ros2Rates(wrench_rate_hz=500))
    assert every_other.take("ft/wrench", wrench) == []
    phase = {"seq": 10, "stamp_ns": 10_000_000, "phase": 2, "posterior": [0.1, 0.2, 0.7],
             "unconditioned": "arm_held"}
    (topic, pe), = view.take("estimator/phase", phase)
    assert topic == "/etar/phase" and pe.phase == 2 and list(pe.posterior) == [0.1, 0.2, 0.7]
    assert (pe.input_fault, pe.unconditioned) == ("", "arm_held")
    back = from_cdr(to_cdr(pe, BY_NAME["/etar/phase"].type), BY_NAME["/etar/phase"].type)
    assert list(back.posterior) == [0.1, 0.2, 0.7] and back.unconditioned == "arm_held"
    assert view.take("robot/command", {"seq": 1}) == []


@pytest.mark.parametrize("rate", [300.0, 0.0, -100.0, 2000.0, float("nan")])
def test_a_rate_that_does_not_divide_the_fri_rate_is_refused_by_name(rate):
    with pytest.raises(ValueError, match=r"wrench_rate_hz must divide the FRI rate 1000 Hz"):
        Ros2Rates(wrench_rate_hz=rate)
