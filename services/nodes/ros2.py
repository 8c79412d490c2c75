"""The ROS 2 node: the cell as ROS 2 sees it, live, on the rmw_zenoh wire.

Takes the robot's state, the sensor's wrench and the phase estimate, turns them into ROS 2
messages (``services.ros2.convert``: the same converter ``etar-bench export --rosbag2``
uses) and hands them to its ROS 2 link (``services.transport.lab.ros2_wire``: one node,
``/etar_cell``, in ``--ros2 DOMAIN``, with its publishers and liveliness tokens on the
service's own Zenoh session).  ``/robot_description`` is published once, when the node
starts, and kept for late subscribers.  It answers no cycle and publishes nothing on the
run's bus, so it cannot change what is recorded or what the cell does; a message it cannot
convert is counted, never the run's problem.

The simulated time runs on across a run's episodes (the FRI cycle count does), so ``/clock``
never goes back within a run.
"""

from __future__ import annotations

from dataclasses import dataclass

from robot_sim.world.tasks import TASK_WORLDS
from services.ros2.convert import Ros2Rates, RosView
from services.ros2.wire import FULL_NODE_NAME, MAX_DOMAIN_ID, check_domain
from services.runtime.bus import Node, Subscription
from services.runtime.config import option
from services.runtime.messages import ESTIMATOR_PHASE, FT_WRENCH, ROBOT_STATE


@dataclass(frozen=True)
class Ros2Config:
    world: str = option("valley", "the task world whose surfaces /robot_description carries", choices=TASK_WORLDS)
    domain: int = option(0, f"ROS 2 domain id, 0..{MAX_DOMAIN_ID} ($ROS_DOMAIN_ID of the machines that look)",
                         metavar="ID")
    state_rate_hz: float = option(Ros2Rates.state_rate_hz, "rate of /joint_states, /tf and /tcp_pose, Hz "
                                                           "(dividing 1000)", metavar="HZ")
    wrench_rate_hz: float = option(Ros2Rates.wrench_rate_hz, "rate of /ft_sensor/wrench, Hz (dividing 1000)",
                                   metavar="HZ")
    clock_rate_hz: float = option(Ros2Rates.clock_rate_hz, "rate of /clock, Hz (dividing 1000)", metavar="HZ")

    def __post_init__(self):
        check_domain(self.domain, "domain")
        self.rates  # Ros2Rates refuses a rate that does not divide the FRI rate, naming its field

    @property
    def rates(self) -> Ros2Rates:
        return Ros2Rates(self.state_rate_hz, self.wrench_rate_hz, self.clock_rate_hz)


class Ros2Node(Node):
    name = "ros2"

    def __init__(self, config: Ros2Config, bus, clock, *, ros2_link=None, **_):
        super().__init__(bus, clock)
        if ros2_link is None:
            raise ValueError("the ros2 role needs a Zenoh session to speak rmw_zenoh on (--transport zenoh)")
        self.view = RosView(config.world, config.rates)
        self.link = ros2_link(config.domain)
        self.errors = 0
        self.link.publish("/robot_description", self.view.description())
        self.subscriptions = [Subscription(ROBOT_STATE.topic, self.on_state),
                              Subscription(FT_WRENCH.topic, self.on_wrench),
                              Subscription(ESTIMATOR_PHASE.topic, self.on_phase)]

    def _take(self, topic: str, msg: dict) -> None:
        try:
            for ros_topic, ros_msg in self.view.take(topic, msg):
                self.link.publish(ros_topic, ros_msg)
        except Exception:  # noqa: BLE001 - ROS 2's view of the run: counted, never the run's problem
            self.errors += 1

    def on_state(self, msg: dict, recv_ns: int, raw: bytes) -> None:
        self._take(ROBOT_STATE.topic, msg)

    def on_wrench(self, msg: dict, recv_ns: int, raw: bytes) -> None:
        self._take(FT_WRENCH.topic, msg)

    def on_phase(self, msg: dict, recv_ns: int, raw: bytes) -> None:
        self._take(ESTIMATOR_PHASE.topic, msg)

    def status(self) -> dict:
        return {"domain": self.link.domain, "node": FULL_NODE_NAME, "sent": dict(self.link.sent),
                "errors": self.errors}

    def close(self) -> None:
        self.link.close()
