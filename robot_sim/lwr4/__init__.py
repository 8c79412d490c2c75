"""The KUKA LWR4+ description: one source of truth for MJCF and URDF."""

from robot_sim.lwr4.description import LWR4, ArmDescription, LinkInertia, ToolDescription

__all__ = ["LWR4", "ArmDescription", "LinkInertia", "ToolDescription"]
