"""The cell's messages as ROS 2 messages: one converter, which the live ``ros2`` node and
the rosbag2 export both drive, so that what a ROS 2 tool sees live is what the bag holds.

``RosView.take(topic, msg)`` turns one of the run's messages (decoded, as the bus or a
recording gives it) into the ROS 2 messages it brings, at the rates ``Ros2Rates`` sets:

- ``robot/state`` -> ``/clock`` (its simulated time), and every n-th FRI cycle
  ``/joint_states`` (the measured joint positions, the joints named as the arm's URDF names
  them), ``/tf`` (each link from its URDF parent, through the KRC's kinematic model,
  Pinocchio) and ``/tcp_pose`` (the measured tcp pose, ``base`` frame);
- ``ft/wrench`` -> ``/ft_sensor/wrench``, the ATI's reading in its frame ``ati_sensor``;
- ``estimator/phase`` -> ``/etar/phase`` (``etar_msgs/msg/PhaseEstimate``), every estimate.

``description()`` is ``/robot_description``: the arm with the task's surfaces as URDF.
Stamps are simulated time (``stamp_ns``).  Pure: no messaging and no files.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from robot_sim.arm.description import LWR4
from robot_sim.cycle import FRI_RATE_HZ
from services.ros2.types import PHASE_ESTIMATE, make
from services.runtime.messages import ESTIMATOR_PHASE, FT_WRENCH, ROBOT_STATE


def _urdf_tree() -> tuple[dict, tuple]:
    """The arm's URDF tree (child link: parent link, parents first) and its moving joints' names."""
    joints = list(ET.fromstring(LWR4.to_urdf()).iter("joint"))
    return ({j.find("child").get("link"): j.find("parent").get("link") for j in joints},
            tuple(j.get("name") for j in joints if j.get("type") == "revolute"))


TF_PARENTS, JOINT_NAMES = _urdf_tree()
BASE_FRAME, SENSOR_FRAME = "base", "ati_sensor"


@dataclass(frozen=True)
class Ros2Rates:
    """How often each ROS 2 topic is published, Hz: every n-th FRI cycle, n = 1000 / rate."""

    state_rate_hz: float = 100.0  # /joint_states, /tf, /tcp_pose: what viewers draw and ros2_control's broadcaster sends
    wrench_rate_hz: float = 1000.0  # /ft_sensor/wrench: every sample the sensor takes
    clock_rate_hz: float = 1000.0  # /clock: one tick per FRI cycle, so use_sim_time nodes can run at 1 kHz

    def __post_init__(self):
        for name in ("state_rate_hz", "wrench_rate_hz", "clock_rate_hz"):
            every_nth(getattr(self, name), name)


def every_nth(rate_hz: float, name: str) -> int:
    """The FRI cycles between two messages at ``rate_hz`` (ValueError naming ``name``)."""
    ok = isinstance(rate_hz, (int, float)) and 0 < rate_hz <= FRI_RATE_HZ
    n = round(FRI_RATE_HZ / rate_hz) if ok else 0
    if not ok or abs(n * rate_hz - FRI_RATE_HZ) > 1e-6 * FRI_RATE_HZ:
        raise ValueError(f"{name} must divide the FRI rate {FRI_RATE_HZ} Hz (1000, 500, 250, 200, 100, 50, ...), "
                         f"got {rate_hz!r}")
    return n


def stamp(ns: int):
    ns = max(int(ns), 0)
    return make("builtin_interfaces/msg/Time", sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def header(ns: int, frame_id: str):
    return make("std_msgs/msg/Header", stamp=stamp(ns), frame_id=frame_id)


class RosView:
    """The ROS 2 messages of a run's messages, for one world at ``rates``."""

    def __init__(self, world: str, rates: Ros2Rates = Ros2Rates()):
        from robot_sim.arm.kinematics import ArmKinematics

        self.world = world
        self.rates = rates
        self._every = {name: every_nth(getattr(rates, name), name)
                       for name in ("state_rate_hz", "wrench_rate_hz", "clock_rate_hz")}
        self.kinematics = ArmKinematics()
        model = self.kinematics.model
        self._frames = [(child, parent, model.getFrameId(child), model.getFrameId(parent))
                        for child, parent in TF_PARENTS.items()]
        self._description = None

    def description(self):
        """``/robot_description``: the arm and the task's surfaces as URDF (built once: it reads
        the world's MuJoCo model)."""
        if self._description is None:
            from robot_sim.world.geometry import viewer_urdf

            self._description = make("std_msgs/msg/String", data=viewer_urdf(self.world))
        return self._description

    def take(self, topic: str, msg: dict) -> list[tuple[str, object]]:
        """The ROS 2 messages (topic name, message) that ``msg`` of run topic ``topic`` brings."""
        if topic == ROBOT_STATE.topic:
            return self._state(msg)
        if topic == FT_WRENCH.topic:
            return [] if msg["seq"] % self._every["wrench_rate_hz"] else [("/ft_sensor/wrench", self._wrench(msg))]
        if topic == ESTIMATOR_PHASE.topic:
            return [("/etar/phase", self._phase(msg))]
        return []

    def _state(self, msg: dict) -> list:
        out = []
        ns, seq = msg["stamp_ns"], msg["seq"]
        if seq % self._every["clock_rate_hz"] == 0:
            out.append(("/clock", make("rosgraph_msgs/msg/Clock", clock=stamp(ns))))
        if seq % self._every["state_rate_hz"] == 0:
            q = np.asarray(msg["msr_jnt_pos"], dtype=np.float64)
            out.append(("/joint_states", make("sensor_msgs/msg/JointState", header=header(ns, ""),
                                              name=list(JOINT_NAMES), position=q.copy(),
                                              velocity=np.empty(0), effort=np.empty(0))))
            out.append(("/tf", self._tf(ns, q)))
            pose = np.asarray(msg["msr_cart_pos"], dtype=np.float64).reshape(3, 4)
            out.append(("/tcp_pose", make("geometry_msgs/msg/PoseStamped", header=header(ns, BASE_FRAME),
                                          pose=_pose(pose[:, :3], pose[:, 3]))))
        return out

    def _tf(self, ns: int, q: np.ndarray):
        kin = self.kinematics
        kin.update_frames(q)
        transforms = []
        for child, parent, cid, pid in self._frames:
            relative = kin.data.oMf[pid].actInv(kin.data.oMf[cid])
            t = relative.translation
            transforms.append(make("geometry_msgs/msg/TransformStamped", header=header(ns, parent), child_frame_id=child,
                                   transform=make("geometry_msgs/msg/Transform", translation=_vector3(t),
                                                  rotation=_quaternion(relative.rotation))))
        return make("tf2_msgs/msg/TFMessage", transforms=transforms)

    def _wrench(self, msg: dict):
        w = msg["wrench"]
        return make("geometry_msgs/msg/WrenchStamped", header=header(msg["stamp_ns"], SENSOR_FRAME),
                    wrench=make("geometry_msgs/msg/Wrench", force=_vector3(w[:3]), torque=_vector3(w[3:])))

    def _phase(self, msg: dict):
        return make(PHASE_ESTIMATE, header=header(msg["stamp_ns"], ""), phase=int(msg["phase"]),
                    posterior=np.asarray(msg["posterior"], dtype=np.float64),
                    input_fault=msg.get("input_fault", ""), unconditioned=msg.get("unconditioned", ""))


def _vector3(v):
    return make("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quaternion(R: np.ndarray):
    import pinocchio as pin

    q = pin.Quaternion(np.asarray(R, dtype=np.float64))
    return make("geometry_msgs/msg/Quaternion", x=float(q.x), y=float(q.y), z=float(q.z), w=float(q.w))


def _pose(R: np.ndarray, p: np.ndarray):
    return make("geometry_msgs/msg/Pose", position=make("geometry_msgs/msg/Point", x=float(p[0]), y=float(p[1]),
                                                        z=float(p[2])), orientation=_quaternion(R))
