"""Task worlds: MuJoCo scenes with the LWR4+ and the task geometry.

``valley()`` is the thesis' fig. 11-12 setup: two aluminium plates at 45 deg
forming a groove along x.  ``hose_coupler()`` is fig. 27: a coupler socket the
tool enters, then turns in.  ``free_space()`` has no task geometry.

Contact: only the tool tip touches the world, through one explicit MuJoCo
``<pair>`` per surface geom (``Surface``: its role and the pair's friction; the
arm's own geoms are visual).  Friction per pair (sliding, torsional, rolling):
steel tip on aluminium plates, sliding 0.25 (dry steel on aluminium is 0.3-0.6
static; a polished tip on anodised plate slides lower), torsional 0.005 m, rolling
1e-4 m; the coupler's rubber seal 0.8 sliding, and torsional 0.8 x the bore's 18 mm
radius (0.0144 m: the seal's friction at its rim, 0.1 N m to turn the hose end at
8 N of press).

How the pair's rows are set, and why (docs/contact.md has the candidates and their
numbers, ``python bench/contact_candidates.py``; MuJoCo's Computation chapter,
"Physical realism and soft contacts", and its modelling guide, "Contact parameters",
are the reference).  MuJoCo's convex contact model couples friction to the normal:
a contact in its sliding zone (friction on the cone, mu N) feeds mu |jar_t| of
separating acceleration into the normal row, jar_t being the friction rows'
residual, the tangential acceleration plus b_f v_t (``mj_constraintUpdate``); the
documentation owns that "complementarity can be violated".  With the friction rows
damped as the normal (b_f = 2 / (0.95 x 20 ms) = 105 /s, the default) a tip sliding
at 5 cm/s floated off a plate in a sawtooth: 20-65 lift-offs a second, single-step
drops of the force to 0 N, 1.7-2.8 N of step-to-step jitter; ten 0.1 ms steps per
cycle did not cure it, stiffer contacts and harder friction made it worse.  Damped
too little (2 /s) the friction rows stop the floating, but their residual is then the
tool's tangential acceleration more than its slip: the friction followed the hand's
10 Hz tremor and fell towards 0 N at each turn of it while the tip slid on (41 % of
the sliding steps more than 10 % off mu).

- ``FRICTION_DAMPING`` = 25 /s: the friction rows' reference damping
  (``solreffriction="0 -25"``, the direct form, which only an explicit pair has).
  b_f v_t outweighs the tremor's accelerations, so sliding friction is mu N (within
  10 % in 96-98 % of the sliding steps), and the separating term is a quarter of the
  default's.
- ``NORMAL_SOLIMP`` = (0.5, 0.95, 1 mm), from (0.9, 0.95, 2 mm): the normal row's
  impedance starts at 0.5 at the surface (nine times the regularisation the
  separating term must overcome) and reaches 0.95 at 1 mm; a tip sliding lightly
  (the teacher pressing 4 N, which its tremor takes to about 1 N) stays on the plate.
  The price: at rest under 8 N the tip sinks 0.54 mm into the plate (0.15 mm before),
  and the landing's peak falls from 36 to 25 N; a stiffer ``solref`` (5-10 ms)
  floated the tip off more, not less.
- ``IMPRATIO`` = 10: friction ten times harder than the normal ("Preventing slip"):
  pressed 8 N on a plate and pushed along it with 1 N (half of mu N), the tip creeps
  0.4 mm/s, where the friction before (impratio 0.01) let it slide at 14.5 mm/s,
  viscous rather than Coulomb.  (impratio 10 alone, the rows at 105 /s, floats the tip
  off 115 times a second.)
- The coupler's torsional friction was 0.1 m, a lever five times the bore's radius:
  turning the hose end floated the tip off the floor as a slide does (with the
  friction rows at 2 /s, the teacher that presses least lifted off 4.3 times a second;
  none with 0.0144 m).

The physics step is ``TIMESTEP`` (one FRI cycle); a world built with a finer
``timestep`` (a whole fraction of it) is the reference the cell is checked against
(``RobotCell(physics_substeps=...)``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from robot_sim.cycle import FRI_CYCLE_NS
from robot_sim.world.labels import LABELERS
from robot_sim.arm.description import ArmDescription, LWR4

TIMESTEP = FRI_CYCLE_NS / 1e9  # s: the physics step, one FRI cycle
IMPRATIO = 10.0  # friction 10 x harder than the normal contact (module docstring)
FRICTION_DAMPING = 25.0  # 1/s: b of the friction rows' reference acceleration (module docstring)
NORMAL_SOLREF = (0.02, 1.5)  # s, damping ratio: the normal direction's reference
NORMAL_SOLIMP = (0.5, 0.95, 0.001)  # impedance at 0 and at 1 mm of penetration (module docstring)


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
    friction: float = 0.8  # sliding friction of the rubber seal on the hose end

    @property
    def torsional_friction(self) -> float:
        """m: the seal grips the hose end at the bore's rim, so turning it costs the seal's
        friction at the bore radius, mu r (0.0144 m: 0.12 N m at 8 N of press)."""
        return self.friction * self.bore_radius


@dataclass(frozen=True)
class Surface:
    """A geom the tool tip touches: its role ('plate', 'coupler') and the pair's friction
    (sliding, torsional m, rolling m)."""

    role: str
    sliding: float
    torsional: float
    rolling: float = 1e-4


@dataclass(frozen=True)
class WorldSpec:
    name: str
    xml: str
    task: object = None
    surfaces: dict = field(default_factory=dict)  # geom name -> Surface

    @property
    def contact_geoms(self) -> dict:
        """geom name -> role of every surface the tip can touch."""
        return {name: s.role for name, s in self.surfaces.items()}

    @property
    def timestep(self) -> float:
        """The physics step the world's XML asks for, s."""
        return float(re.search(r'<option timestep="([^"]+)"', self.xml).group(1))


def physics_step(substeps: int) -> float:
    """The physics step, s, of ``substeps`` whole nanosecond steps per FRI cycle."""
    if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1 or FRI_CYCLE_NS % substeps:
        raise ValueError(f"physics substeps must be a whole divisor of the {FRI_CYCLE_NS} ns FRI cycle (1, 2, 4, "
                         f"5, 10, 20, ...), got {substeps!r}")
    return FRI_CYCLE_NS // substeps / 1e9


def _header(name: str, timestep: float) -> str:
    substeps = round(TIMESTEP / timestep) if timestep > 0 else 0
    if not (substeps >= 1 and FRI_CYCLE_NS % substeps == 0 and physics_step(substeps) == timestep):
        raise ValueError(f"world {name}: the physics step must be a whole fraction of {TIMESTEP} s in whole "
                         f"nanoseconds, got {timestep!r}")
    return f"""<mujoco model="{name}">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{timestep!r}" integrator="implicitfast" gravity="0 0 -9.81" cone="elliptic" impratio="{IMPRATIO!r}"/>
  <default>
    <pair condim="4" solref="{_f(NORMAL_SOLREF)}" solimp="{_f(NORMAL_SOLIMP)}" solreffriction="0 {-FRICTION_DAMPING!r}"/>
  </default>
  <visual><global offwidth="960" offheight="720"/></visual>
  <worldbody>
    <light pos="0.5 -1 2" dir="-0.2 0.5 -1"/>
    <geom name="floor" type="plane" size="2 2 0.1" rgba="0.85 0.85 0.8 1" contype="0" conaffinity="0"/>
"""


def _footer(surfaces: dict | None = None) -> str:
    pairs = "".join(f'    <pair geom1="tool_tip" geom2="{name}" '
                    f'friction="{_f((s.sliding, s.sliding, s.torsional, s.rolling, s.rolling))}"/>\n'
                    for name, s in (surfaces or {}).items())
    contact = f"  <contact>\n{pairs}  </contact>\n" if pairs else ""
    return """  </worldbody>
""" + contact + """  <sensor>
    <force name="ft_force" site="ft_site"/>
    <torque name="ft_torque" site="ft_site"/>
  </sensor>
</mujoco>
"""


def free_space(description: ArmDescription = LWR4, timestep: float = TIMESTEP) -> WorldSpec:
    xml = _header("free_space", timestep) + description.mjcf_arm() + "\n" + _footer()
    return WorldSpec("free_space", xml)


def valley(geometry: Valley = Valley(), description: ArmDescription = LWR4, timestep: float = TIMESTEP) -> WorldSpec:
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
            f'size="{length / 2!r} {slope / 2!r} {g.thickness / 2!r}" contype="0" conaffinity="0" '
            'rgba="0.75 0.77 0.8 1"/>'
        )
    stand = (
        f'    <geom name="valley_stand" type="box" pos="{xc!r} 0 {(g.groove_z - 0.02) / 2!r}" '
        f'size="{length / 2!r} 0.02 {(g.groove_z - 0.02) / 2!r}" contype="0" conaffinity="0" rgba="0.4 0.4 0.45 1"/>'
    )
    plate = Surface("plate", g.friction, 0.005)
    surfaces = {"plate_left": plate, "plate_right": plate}
    xml = (_header("valley", timestep) + "\n".join(plates) + "\n" + stand + "\n" + description.mjcf_arm() + "\n"
           + _footer(surfaces))
    return WorldSpec("valley", xml, g, surfaces)


def hose_coupler(geometry: HoseCoupler = HoseCoupler(), description: ArmDescription = LWR4,
                 timestep: float = TIMESTEP) -> WorldSpec:
    g = geometry
    cx, cy, cz = g.center
    wall = 0.01
    parts = [
        f'    <geom name="coupler_floor" type="cylinder" pos="{cx!r} {cy!r} {cz - 0.005!r}" '
        f'size="{g.bore_radius + wall!r} 0.005" contype="0" conaffinity="0" rgba="0.1 0.1 0.1 1"/>',
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
            f'contype="0" conaffinity="0" rgba="0.15 0.15 0.15 1"/>'
        )
    seal = Surface("coupler", g.friction, g.torsional_friction)
    surfaces = {"coupler_floor": seal} | {f"coupler_wall{k}": seal for k in range(n_wall)}
    xml = (_header("hose_coupler", timestep) + "\n".join(parts) + "\n" + description.mjcf_arm() + "\n"
           + _footer(surfaces))
    return WorldSpec("hose_coupler", xml, g, surfaces)


WORLDS = {"free_space": free_space, "valley": valley, "hose_coupler": hose_coupler}
# the worlds with a task: a teacher to demonstrate it, true phases to label it
TASK_WORLDS = tuple(LABELERS)
assert set(TASK_WORLDS) <= set(WORLDS)


def _f(values) -> str:
    return " ".join(repr(float(v)) for v in values)
