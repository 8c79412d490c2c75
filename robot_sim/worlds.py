"""Task worlds: MuJoCo scenes with the LWR4+ and the task geometry.

``valley()`` is the thesis' fig. 11-12 setup: two aluminium plates at 45 deg
forming a groove along x.  ``hose_coupler()`` is fig. 27: a coupler socket the
tool enters, then turns in.  ``free_space()`` has no task geometry.

Contact: only the tool tip collides (the arm's capsules are visual), with
geoms of contype 1 / conaffinity 2.  MuJoCo takes the larger friction of the
two geoms in contact, so the tip's own friction is set low (0.1) and each
surface carries the pair's coefficients (sliding, torsional, rolling): steel
tip on aluminium, sliding 0.25 (dry steel on aluminium is
0.3-0.6 static; a polished tip on anodised plate slides lower), torsional
0.005 m, rolling 1e-4 m; the coupler's rubber seal 0.8 sliding and 0.1 m
torsional so that turning the hose end costs a measurable torque.
Contact softness solref = (5 ms, 1): stiff, critically damped, stable at the
1 ms step.  ``impratio = 0.01`` makes friction softer than the normal
contact: with the default (1) a tip sliding on a plate under the arm's
inertia chattered on and off the surface at ~170 Hz (friction impulses
kicking it off through the arm's mass matrix; contact present in 76 % of the
steps), with 0.01 it stays in contact (98 %) and the sliding friction is
still mu N (measured 1.95 N at 7.8 N normal force, mu = 0.25).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from robot_sim.fri import FRI_CYCLE_NS
from robot_sim.labels import LABELERS
from robot_sim.lwr4.description import LWR4, ArmDescription

TIMESTEP = FRI_CYCLE_NS / 1e9  # s: the physics step, one FRI cycle


@dataclass(frozen=True)
class Valley:
    """Geometry of the valley: the groove runs along x at (y = 0, z = groove_z)."""

    groove_z: float = 0.20
    x_start: float = 0.32
    x_end: float = 0.78
    half_width: float = 0.16  # m, horizontal extent of each plate from the groove
    thickness: float = 0.006
    angle: float = math.pi / 4
    friction: float = 0.25  # sliding friction coefficient of the plates (aluminium on the tool tip)
    # where a demonstration starts by default: the tcp above the left plate (the right side
    # mirrors y), and where the teacher stops sliding along the groove (towards -x)
    start_left: tuple = (0.68, -0.10, 0.40)
    goal_x: float = 0.42

    def plate_normal(self, side: int) -> np.ndarray:
        """Unit normal of the plate on side -1 (y < 0) or +1 (y > 0), pointing into the valley."""
        return np.array([0.0, -side * math.sin(self.angle), math.cos(self.angle)])

    def surface_z(self, y: float) -> float:
        return self.groove_z + abs(y) * math.tan(self.angle)


@dataclass(frozen=True)
class HoseCoupler:
    """A cup-shaped socket on a post; the hose end (tool tip) enters and turns."""

    center: tuple = (0.55, 0.0, 0.20)  # top face centre of the socket floor, m
    bore_radius: float = 0.018
    depth: float = 0.03
    start_left: tuple = (0.62, -0.08, 0.36)  # the default tcp start: above and beside the socket


@dataclass(frozen=True)
class WorldSpec:
    name: str
    xml: str
    task: object = None
    contact_geoms: dict = field(default_factory=dict)  # geom name -> role


def _header(name: str) -> str:
    return f"""<mujoco model="{name}">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{TIMESTEP!r}" integrator="implicitfast" gravity="0 0 -9.81" cone="elliptic" impratio="0.01"/>
  <default>
    <geom solref="0.02 1.5" solimp="0.9 0.95 0.002"/>
  </default>
  <visual><global offwidth="960" offheight="720"/></visual>
  <worldbody>
    <light pos="0.5 -1 2" dir="-0.2 0.5 -1"/>
    <geom name="floor" type="plane" size="2 2 0.1" rgba="0.85 0.85 0.8 1" contype="0" conaffinity="0"/>
"""


def _footer() -> str:
    return """  </worldbody>
  <sensor>
    <force name="ft_force" site="ft_site"/>
    <torque name="ft_torque" site="ft_site"/>
  </sensor>
</mujoco>
"""


def free_space(description: ArmDescription = LWR4) -> WorldSpec:
    xml = _header("free_space") + description.mjcf_arm() + "\n" + _footer()
    return WorldSpec("free_space", xml)


def valley(geometry: Valley = Valley(), description: ArmDescription = LWR4) -> WorldSpec:
    g = geometry
    plates = []
    length = g.x_end - g.x_start
    xc = 0.5 * (g.x_start + g.x_end)
    slope = g.half_width / math.cos(g.angle)
    for side, name in ((-1, "plate_left"), (1, "plate_right")):
        n = g.plate_normal(side)
        # the plate's top surface passes through the groove line and rises outwards
        centre_surface = np.array([xc, side * g.half_width / 2, g.surface_z(g.half_width / 2)])
        centre = centre_surface - n * g.thickness / 2
        # box axes: x along the groove, y up the slope, z the normal
        angle = side * g.angle
        quat = (math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0)
        plates.append(
            f'    <geom name="{name}" type="box" pos="{_f(centre)}" quat="{_f(quat)}" '
            f'size="{length / 2!r} {slope / 2!r} {g.thickness / 2!r}" contype="1" conaffinity="2" '
            f'condim="4" friction="{g.friction!r} 0.005 0.0001" rgba="0.75 0.77 0.8 1"/>'
        )
    stand = (
        f'    <geom name="valley_stand" type="box" pos="{xc!r} 0 {(g.groove_z - 0.02) / 2!r}" '
        f'size="{length / 2!r} 0.02 {(g.groove_z - 0.02) / 2!r}" contype="0" conaffinity="0" rgba="0.4 0.4 0.45 1"/>'
    )
    xml = _header("valley") + "\n".join(plates) + "\n" + stand + "\n" + description.mjcf_arm() + "\n" + _footer()
    return WorldSpec("valley", xml, g, {"plate_left": "plate", "plate_right": "plate"})


def hose_coupler(geometry: HoseCoupler = HoseCoupler(), description: ArmDescription = LWR4) -> WorldSpec:
    g = geometry
    cx, cy, cz = g.center
    wall = 0.01
    parts = [
        f'    <geom name="coupler_floor" type="cylinder" pos="{cx!r} {cy!r} {cz - 0.005!r}" '
        f'size="{g.bore_radius + wall!r} 0.005" contype="1" conaffinity="2" condim="4" '
        f'friction="0.8 0.1 0.0001" rgba="0.1 0.1 0.1 1"/>',
        f'    <geom name="coupler_post" type="cylinder" pos="{cx!r} {cy!r} {(cz - 0.01) / 2!r}" '
        f'size="0.03 {(cz - 0.01) / 2!r}" contype="0" conaffinity="0" rgba="0.3 0.3 0.35 1"/>',
    ]
    n_wall = 12
    for k in range(n_wall):
        a = 2 * math.pi * k / n_wall
        r = g.bore_radius + wall / 2
        quat = (math.cos(a / 2), 0.0, 0.0, math.sin(a / 2))
        chord = 2 * (g.bore_radius + wall) * math.tan(math.pi / n_wall)
        parts.append(
            f'    <geom name="coupler_wall{k}" type="box" pos="{cx + r * math.cos(a)!r} {cy + r * math.sin(a)!r} '
            f'{cz + g.depth / 2!r}" quat="{_f(quat)}" size="{wall / 2!r} {chord / 2!r} {g.depth / 2!r}" '
            f'contype="1" conaffinity="2" condim="4" friction="0.8 0.1 0.0001" rgba="0.15 0.15 0.15 1"/>'
        )
    xml = _header("hose_coupler") + "\n".join(parts) + "\n" + description.mjcf_arm() + "\n" + _footer()
    roles = {"coupler_floor": "coupler"} | {f"coupler_wall{k}": "coupler" for k in range(n_wall)}
    return WorldSpec("hose_coupler", xml, g, roles)


WORLDS = {"free_space": free_space, "valley": valley, "hose_coupler": hose_coupler}
# the worlds with a task: a teacher to demonstrate it, true phases to label it
TASK_WORLDS = tuple(LABELERS)
assert set(TASK_WORLDS) <= set(WORLDS)


def _f(values) -> str:
    return " ".join(repr(float(v)) for v in values)
