"""What the cell looks like, read from the MuJoCo model the physics runs: every geom of a
world (the task's surfaces and the arm's links) as a shape on a frame, and the arm's URDF
with those shapes as its visuals, for viewers that draw a robot from its description
(rviz2, Foxglove's URDF layer, through ``/robot_description``).

The MuJoCo bodies carry the URDF's link names (``robot_sim.arm.description``), so a
geom's pose in its body is its pose in the link of that name; the world's own geoms sit
on ``base``.  The KRC's URDF (``ArmDescription.to_urdf``, what Pinocchio reads) stays
without visuals: what a viewer draws cannot change the model the controller runs.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Geom:
    frame: str  # "base" (the world's) or the link the geom moves with
    shape: str  # "box" | "sphere" | "cylinder" (a capsule is drawn as a cylinder with its caps' length)
    position: tuple  # (3,) m, in the frame
    quaternion: tuple  # (w, x, y, z), in the frame
    size: tuple  # full extents, m: box (x, y, z), sphere (d, d, d), cylinder (d, d, length)
    rgba: tuple


def world_geoms(world: str) -> tuple[Geom, ...]:
    """Every drawable geom of ``world``'s MuJoCo model.  Planes (the floor) are left out:
    viewers draw a grid of their own."""
    import mujoco

    from robot_sim.world.tasks import WORLDS

    if world not in WORLDS:
        raise ValueError(f"unknown world {world!r}: expected one of {', '.join(WORLDS)}")
    m = mujoco.MjModel.from_xml_string(WORLDS[world]().xml)
    out = []
    for g in range(m.ngeom):
        kind = int(m.geom_type[g])
        body = int(m.geom_bodyid[g])
        frame = "base" if body == 0 else m.body(body).name
        size = m.geom_size[g]
        if kind == mujoco.mjtGeom.mjGEOM_BOX:
            shape, dims = "box", [2 * size[0], 2 * size[1], 2 * size[2]]
        elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            shape, dims = "sphere", [2 * size[0]] * 3
        elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
            shape, dims = "cylinder", [2 * size[0], 2 * size[0], 2 * size[1]]
        elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
            # a cylinder as long as the capsule with its caps: near enough to see the link
            shape, dims = "cylinder", [2 * size[0], 2 * size[0], 2 * size[1] + 2 * size[0]]
        else:
            continue
        out.append(Geom(frame, shape, tuple(float(x) for x in m.geom_pos[g]),
                        tuple(float(x) for x in m.geom_quat[g]), tuple(float(d) for d in dims),
                        tuple(float(c) for c in m.geom_rgba[g])))
    return tuple(out)


def viewer_urdf(world: str) -> str:
    """The arm's URDF (its links, joints and frames as the KRC has them) with every geom of
    ``world`` as a ``<visual>`` of its link: the task's surfaces on ``base``."""
    from robot_sim.arm.description import LWR4

    robot = ET.fromstring(LWR4.to_urdf())
    links = {link.get("name"): link for link in robot.iter("link")}
    for i, geom in enumerate(world_geoms(world)):
        link = links.get(geom.frame)
        if link is None:
            raise ValueError(f"world {world!r}: geom {i} is on body {geom.frame!r}, which the arm's URDF lacks")
        visual = ET.SubElement(link, "visual", name=f"geom{i}")
        ET.SubElement(visual, "origin", xyz=_xyz(geom.position), rpy=_xyz(_rpy(geom.quaternion)))
        shape = ET.SubElement(visual, "geometry")
        if geom.shape == "box":
            ET.SubElement(shape, "box", size=_xyz(geom.size))
        elif geom.shape == "sphere":
            ET.SubElement(shape, "sphere", radius=repr(geom.size[0] / 2))
        else:
            ET.SubElement(shape, "cylinder", radius=repr(geom.size[0] / 2), length=repr(geom.size[2]))
        material = ET.SubElement(visual, "material", name=f"geom{i}")
        ET.SubElement(material, "color", rgba=" ".join(f"{c:.6g}" for c in geom.rgba))
    return ET.tostring(robot, encoding="unicode")


def _rpy(quaternion) -> tuple:
    """URDF's roll, pitch, yaw (fixed axes x, y, z) of a (w, x, y, z) quaternion."""
    from scipy.spatial.transform import Rotation

    w, x, y, z = quaternion
    return tuple(float(a) for a in Rotation.from_quat(np.array([x, y, z, w])).as_euler("xyz"))


def _xyz(values) -> str:
    return " ".join(repr(float(v)) for v in values)
