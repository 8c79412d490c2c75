"""The roles of the cell as nodes (``services.runtime.bus``): each takes decoded
messages and the time, answers control requests and publishes through a bus.
``services.transport.process`` carries one in its own process over Zenoh,
``services.transport.inproc`` all of them in one process.

A node's module is imported when its role is first asked for (``NODES[role]``, or a
class by name: ``from services.nodes import RobotConfig``), not with this package: a
service process runs one node, and importing all seven (the robot's MuJoCo, the sensor's
compiled kernels, numba, scipy) cost every process of a run about a second of CPU at
start-up that most of them never use (docs/benchmarks.md, "Start-up").  Asking whether a
role is known imports nothing; ``NODES.values()`` and ``.items()`` import every node.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from importlib import import_module

from services.runtime.roles import ROLES

# role -> (the node class, its config class), both in the module of this package named
# after the role
_CLASSES = {
    "robot": ("RobotNode", "RobotConfig"),
    "ft_sensor": ("FtSensorNode", "FtSensorConfig"),
    "teacher": ("TeacherNode", "TeacherConfig"),
    "phase_estimator": ("PhaseEstimatorNode", "EstimatorConfig"),
    "impedance_commander": ("ImpedanceCommanderNode", "CommanderConfig"),
    "recorder": ("RecorderNode", "RecorderConfig"),
    "foxglove_bridge": ("FoxgloveBridgeNode", "FoxgloveBridgeConfig"),
    "ros2": ("Ros2Node", "Ros2Config"),
}
assert _CLASSES.keys() == ROLES.keys(), "every role of services.runtime.roles has its node, and no other"
_MODULE_OF = {cls: role for role, classes in _CLASSES.items() for cls in classes}


class _Nodes(Mapping):
    """role -> (node class, its config class), each module imported on first use."""

    def __getitem__(self, role: str):
        node, config = _CLASSES[role]
        loaded = import_module(f"{__name__}.{role}")
        return getattr(loaded, node), getattr(loaded, config)

    def __contains__(self, role) -> bool:  # Mapping's would import the role's module
        return role in _CLASSES

    def __iter__(self) -> Iterator[str]:
        return iter(_CLASSES)

    def __len__(self) -> int:
        return len(_CLASSES)


NODES = _Nodes()


def __getattr__(name: str):
    """``from services.nodes import RobotConfig``: the class from its node's module."""
    if name in _MODULE_OF:
        return getattr(import_module(f"{__name__}.{_MODULE_OF[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_MODULE_OF])
