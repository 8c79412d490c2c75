"""The roles of the cell as nodes (``services.runtime.bus``): each takes decoded
messages and the time, answers control requests and publishes through a bus.
``services.transport.process`` carries one in its own process over Zenoh,
``services.transport.inproc`` all of them in one process."""

from services.nodes.foxglove_bridge import FoxgloveBridgeConfig, FoxgloveBridgeNode
from services.nodes.ft_sensor import FtSensorConfig, FtSensorNode
from services.nodes.impedance_commander import CommanderConfig, ImpedanceCommanderNode
from services.nodes.phase_estimator import EstimatorConfig, PhaseEstimatorNode
from services.nodes.recorder import RecorderConfig, RecorderNode
from services.nodes.robot import RobotConfig, RobotNode
from services.nodes.teacher import TeacherConfig, TeacherNode
from services.runtime.roles import ROLES

# role -> (node class, its config class)
NODES = {
    "robot": (RobotNode, RobotConfig),
    "ft_sensor": (FtSensorNode, FtSensorConfig),
    "teacher": (TeacherNode, TeacherConfig),
    "phase_estimator": (PhaseEstimatorNode, EstimatorConfig),
    "impedance_commander": (ImpedanceCommanderNode, CommanderConfig),
    "recorder": (RecorderNode, RecorderConfig),
    "foxglove_bridge": (FoxgloveBridgeNode, FoxgloveBridgeConfig),
}
assert NODES.keys() == ROLES.keys(), "every role of services.runtime.roles has its node, and no other"
