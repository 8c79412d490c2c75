"""The roles of the cell as nodes (``services.runtime.bus``): each takes decoded
messages and the time, answers control requests and publishes through a bus.
``services.transport.process`` carries one in its own process over Zenoh,
``services.transport.inproc`` all of them in one process.

A node's module is imported when its role is first asked for (``NODES[role]``, or a
class by name: ``from services.nodes import RobotConfig``), not with this package: a
service process runs one node, and importing all seven cost each of the seven processes
of a run ~1.8 s of CPU at start-up (the robot's MuJoCo, the sensor's compiled kernels,
numba and scipy), where the recorder alone needs 0.4 s (docs/benchmarks.md).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from importlib import import_module

from services.runtime.roles import ROLES

# role -> (its module in this package, the node class, its config class)
_WHERE = {
    "robot": ("robot", "RobotNode", "RobotConfig"),
    "ft_sensor": ("ft_sensor", "FtSensorNode", "FtSensorConfig"),
    "teacher": ("teacher", "TeacherNode", "TeacherConfig"),
    "phase_estimator": ("phase_estimator", "PhaseEstimatorNode", "EstimatorConfig"),
    "impedance_commander": ("impedance_commander", "ImpedanceCommanderNode", "CommanderConfig"),
    "recorder": ("recorder", "RecorderNode", "RecorderConfig"),
    "foxglove_bridge": ("foxglove_bridge", "FoxgloveBridgeNode", "FoxgloveBridgeConfig"),
}
assert _WHERE.keys() == ROLES.keys(), "every role of services.runtime.roles has its node, and no other"
_MODULE_OF = {cls: module for module, *classes in _WHERE.values() for cls in classes}


class _Nodes(Mapping):
    """role -> (node class, its config class), each module imported on first use."""

    def __getitem__(self, role: str):
        module, node, config = _WHERE[role]
        loaded = import_module(f"{__name__}.{module}")
        return getattr(loaded, node), getattr(loaded, config)

    def __iter__(self) -> Iterator[str]:
        return iter(_WHERE)

    def __len__(self) -> int:
        return len(_WHERE)


NODES = _Nodes()


def __getattr__(name: str):
    """``from services.nodes import RobotConfig``: the class from its node's module."""
    if name in _MODULE_OF:
        return getattr(import_module(f"{__name__}.{_MODULE_OF[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_MODULE_OF])
