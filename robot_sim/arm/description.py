"""KUKA LWR4+ with an ATI sensor and a round-tipped tool, described once.

``to_urdf()`` (for Pinocchio) and ``mjcf_arm()`` (for MuJoCo) are both generated
from ``ArmDescription``; ``tests/robot_sim/test_model_agreement.py`` checks that
the two agree on forward kinematics, Jacobians and gravity torques.

Kinematics: standard DH (DESIGN.md, from the KUKA FRI documentation),
T = prod_i Rz(q_i) Tz(d_i) Rx(alpha_i).  In both formats joint i rotates about
the z axis of link i's frame, and link i+1's frame sits at Tz(d_i) Rx(alpha_i)
in link i's frame; the flange is Tz(d_7) after link 7.

Limits, speeds, torques: DESIGN.md (KUKA LWR4+ data sheet).

Masses: the LWR4+ weighs 15 kg (data sheet).  KUKA does not publish link
inertial parameters; the masses below (2.7, 2.7, 2.7, 2.7, 1.7, 1.6, 0.3 kg =
14.4 kg, the rest being the fixed base housing) follow the identified values of
Jubien, Gautier & Janot, "Dynamic identification of the Kuka LightWeight robot:
comparison between actual and confidential Kuka's parameters", AIM 2014, and
sit beside pybullet's iiwa URDF (4/4/3/2.7/1.7/1.8/0.3 kg) as a sanity check.
Each link is modelled as a solid aluminium-shell cylinder of radius 0.06 m
along its segment (inertia from the cylinder formula), centre of mass placed
along the segment; good enough for gravity and inertia effects of the right
size, not an identified model.

Joint damping 0.3 N m s/rad and armature (reflected rotor inertia)
0.08 kg m^2 are applied in MuJoCo only: the KRC's model (Pinocchio) does not
know them, as a real controller does not know its friction exactly.

Sensor and tool: ATI Mini45 (diameter 45 mm, height 15.7 mm, 92 g; ATI data
sheet), then a steel rod 0.12 m long, 12 mm radius, 0.25 kg, ending in a
10 mm-radius sphere (the rounded tip).  Frames: ``flange`` (DH frame 7),
``ati_sensor`` (the sensor's measuring face, 15.7 mm above the flange along
its z), ``tcp`` (centre of the tip sphere).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

DEG = math.pi / 180.0


@dataclass(frozen=True)
class LinkInertia:
    mass: float  # kg
    com: tuple  # (3,) m, in the link frame
    inertia: tuple  # (ixx, iyy, izz, ixy, ixz, iyz) about the COM, link-frame axes


@dataclass(frozen=True)
class ToolDescription:
    sensor_height: float = 0.0157  # m, Mini45
    sensor_radius: float = 0.0225
    sensor_mass: float = 0.092
    rod_length: float = 0.12
    rod_radius: float = 0.012
    rod_mass: float = 0.25
    tip_radius: float = 0.010

    @property
    def sensor_to_tcp(self) -> float:
        """Distance from the sensor's measuring face to the tip sphere's centre."""
        return self.rod_length


@dataclass(frozen=True)
class ArmDescription:
    name: str
    d: tuple
    a: tuple
    alpha: tuple
    q_min: tuple  # rad
    q_max: tuple
    qd_max: tuple  # rad/s
    tau_max: tuple  # N m
    links: tuple  # 7 LinkInertia
    joint_damping: float = 2.0
    armature: float = 0.08
    tool: ToolDescription = field(default_factory=ToolDescription)

    @property
    def n_joints(self) -> int:
        return len(self.d)

    def joint_origin(self, i: int):
        """(xyz, rpy) of joint i (0-based) in the parent link frame."""
        if i == 0:
            return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
        return (0.0, 0.0, self.d[i - 1]), (self.alpha[i - 1], 0.0, 0.0)

    # ------------------------------------------------------------------ URDF

    def to_urdf(self) -> str:
        """URDF for Pinocchio: arm, fixed flange, sensor, tool and tcp frames."""
        t = self.tool
        parts = [f'<robot name="{self.name}">', '  <link name="base"/>']
        parent = "base"
        for i in range(self.n_joints):
            xyz, rpy = self.joint_origin(i)
            li = self.links[i]
            ixx, iyy, izz, ixy, ixz, iyz = li.inertia
            parts += [
                f'  <joint name="joint{i + 1}" type="revolute">',
                f'    <parent link="{parent}"/><child link="link{i + 1}"/>',
                f'    <origin xyz="{_f(xyz)}" rpy="{_f(rpy)}"/><axis xyz="0 0 1"/>',
                f'    <limit lower="{self.q_min[i]!r}" upper="{self.q_max[i]!r}" '
                f'effort="{self.tau_max[i]!r}" velocity="{self.qd_max[i]!r}"/>',
                "  </joint>",
                f'  <link name="link{i + 1}"><inertial><origin xyz="{_f(li.com)}" rpy="0 0 0"/>',
                f'    <mass value="{li.mass!r}"/>',
                f'    <inertia ixx="{ixx!r}" iyy="{iyy!r}" izz="{izz!r}" ixy="{ixy!r}" ixz="{ixz!r}" iyz="{iyz!r}"/>',
                "  </inertial></link>",
            ]
            parent = f"link{i + 1}"
        sensor = _cylinder_inertia(t.sensor_mass, t.sensor_radius, t.sensor_height)
        rod = _cylinder_inertia(t.rod_mass, t.rod_radius, t.rod_length)
        parts += [
            '  <joint name="flange_joint" type="fixed"><parent link="link7"/><child link="flange"/>',
            f'    <origin xyz="0 0 {self.d[6]!r}" rpy="{self.alpha[6]!r} 0 0"/></joint>',
            '  <link name="flange"/>',
            '  <joint name="sensor_joint" type="fixed"><parent link="flange"/><child link="ati_sensor"/>',
            f'    <origin xyz="0 0 {t.sensor_height!r}" rpy="0 0 0"/></joint>',
            '  <link name="ati_sensor"><inertial>',
            f'    <origin xyz="0 0 {-t.sensor_height / 2!r}" rpy="0 0 0"/><mass value="{t.sensor_mass!r}"/>',
            f'    <inertia ixx="{sensor[0]!r}" iyy="{sensor[1]!r}" izz="{sensor[2]!r}" ixy="0" ixz="0" iyz="0"/>',
            "  </inertial></link>",
            '  <joint name="tool_joint" type="fixed"><parent link="ati_sensor"/><child link="tool"/>',
            '    <origin xyz="0 0 0" rpy="0 0 0"/></joint>',
            '  <link name="tool"><inertial>',
            f'    <origin xyz="0 0 {t.rod_length / 2!r}" rpy="0 0 0"/><mass value="{t.rod_mass!r}"/>',
            f'    <inertia ixx="{rod[0]!r}" iyy="{rod[1]!r}" izz="{rod[2]!r}" ixy="0" ixz="0" iyz="0"/>',
            "  </inertial></link>",
            '  <joint name="tcp_joint" type="fixed"><parent link="tool"/><child link="tcp"/>',
            f'    <origin xyz="0 0 {t.sensor_to_tcp!r}" rpy="0 0 0"/></joint>',
            '  <link name="tcp"/>',
            "</robot>",
        ]
        return "\n".join(parts)

    # ------------------------------------------------------------------ MJCF

    def mjcf_arm(self, base_pos=(0.0, 0.0, 0.0)) -> str:
        """The arm as an MJCF <body> tree (for a world's <worldbody>).

        Bodies ``link1..link7``, ``ati_sensor``, ``tool``; joints ``joint1..7``;
        sites ``flange``, ``ft_site`` (sensor face, on the tool body: MuJoCo's
        force/torque sensors there measure what the tool transmits to the
        sensor) and ``tcp``; the tip geom ``tool_tip``.  No geom collides by its
        contype: a world pairs the tip with each surface it can touch
        (``robot_sim.world.tasks``), so the pair, not the geoms, says how they meet.
        """
        t = self.tool
        lines = []
        indent = "    "
        for i in range(self.n_joints):
            xyz, rpy = self.joint_origin(i)
            if i == 0:
                xyz = tuple(base_pos)
            li = self.links[i]
            ixx, iyy, izz, ixy, ixz, iyz = li.inertia
            seg = self._segment(i)
            lines.append(f'{indent}<body name="link{i + 1}" pos="{_f(xyz)}" quat="{_f(_quat_rx(rpy[0]))}">')
            lines.append(
                f'{indent}  <inertial pos="{_f(li.com)}" mass="{li.mass!r}" '
                f'fullinertia="{ixx!r} {iyy!r} {izz!r} {ixy!r} {ixz!r} {iyz!r}"/>'
            )
            lines.append(
                f'{indent}  <joint name="joint{i + 1}" axis="0 0 1" range="{self.q_min[i]!r} {self.q_max[i]!r}" '
                f'damping="{self.joint_damping!r}" armature="{self.armature!r}" limited="true"/>'
            )
            if np.linalg.norm(seg) > 1e-9:
                lines.append(
                    f'{indent}  <geom type="capsule" fromto="0 0 0 {_f(seg)}" size="0.06" '
                    'contype="0" conaffinity="0" rgba="1 0.5 0.1 1" mass="0"/>'
                )
            indent += "  "
        lines += [
            f'{indent}<site name="flange" pos="0 0 {self.d[6]!r}"/>',
            f'{indent}<body name="ati_sensor" pos="0 0 {self.d[6] + t.sensor_height!r}">',
            f'{indent}  <inertial pos="0 0 {-t.sensor_height / 2!r}" mass="{t.sensor_mass!r}" '
            f'diaginertia="{_f(_cylinder_inertia(t.sensor_mass, t.sensor_radius, t.sensor_height))}"/>',
            f'{indent}  <geom type="cylinder" pos="0 0 {-t.sensor_height / 2!r}" '
            f'size="{t.sensor_radius!r} {t.sensor_height / 2!r}" contype="0" conaffinity="0" '
            'rgba="0.6 0.6 0.6 1" mass="0"/>',
            f'{indent}  <body name="tool" pos="0 0 0">',
            f'{indent}    <inertial pos="0 0 {t.rod_length / 2!r}" mass="{t.rod_mass!r}" '
            f'diaginertia="{_f(_cylinder_inertia(t.rod_mass, t.rod_radius, t.rod_length))}"/>',
            f'{indent}    <site name="ft_site" pos="0 0 0"/>',
            f'{indent}    <geom name="tool_rod" type="cylinder" pos="0 0 {t.rod_length / 2!r}" '
            f'size="{t.rod_radius!r} {t.rod_length / 2 - t.tip_radius!r}" contype="0" conaffinity="0" '
            'rgba="0.3 0.3 0.35 1" mass="0"/>',
            f'{indent}    <geom name="tool_tip" type="sphere" pos="0 0 {t.sensor_to_tcp!r}" size="{t.tip_radius!r}" '
            'contype="0" conaffinity="0" rgba="0.2 0.2 0.25 1" mass="0"/>',
            f'{indent}    <site name="tcp" pos="0 0 {t.sensor_to_tcp!r}"/>',
            f"{indent}  </body>",
            f"{indent}</body>",
        ]
        for i in range(self.n_joints):
            indent = indent[:-2]
            lines.append(f"{indent}</body>")
        return "\n".join(lines)

    def _segment(self, i: int) -> np.ndarray:
        """Vector from joint i to joint i+1 (or the flange) in link i's frame."""
        return np.array([0.0, 0.0, self.d[i]])


def _f(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def _quat_rx(angle: float):
    return (math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0)


def _cylinder_inertia(mass: float, radius: float, length: float):
    """(ixx, iyy, izz) of a solid cylinder along z about its centre."""
    perp = mass * (3 * radius**2 + length**2) / 12.0
    return (perp, perp, mass * radius**2 / 2.0)


def _link_inertia(mass: float, seg_start, seg_end, com_fraction: float, radius: float = 0.06) -> LinkInertia:
    """A cylinder of ``mass`` from seg_start to seg_end (link frame), COM at a fraction."""
    p0, p1 = np.asarray(seg_start, float), np.asarray(seg_end, float)
    axis = p1 - p0
    length = max(np.linalg.norm(axis), 2 * radius)
    u = axis / np.linalg.norm(axis)
    perp, _, ax = _cylinder_inertia(mass, radius, length)
    I = perp * np.eye(3) + (ax - perp) * np.outer(u, u)
    com = p0 + com_fraction * axis
    inertia = (I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2])
    return LinkInertia(float(mass), tuple(float(c) for c in com), tuple(float(v) for v in inertia))


def _lwr4() -> ArmDescription:
    d = (0.3105, 0.0, 0.4, 0.0, 0.39, 0.0, 0.078)
    alpha = (math.pi / 2, -math.pi / 2, -math.pi / 2, math.pi / 2, math.pi / 2, -math.pi / 2, 0.0)
    lim = (170, 120, 170, 120, 170, 120, 170)
    speeds = (110, 110, 128, 128, 204, 184, 184)
    masses = (2.7, 2.7, 2.7, 2.7, 1.7, 1.6, 0.3)
    # Where the mass of each link lies (link frame): links 1, 3, 5, 7 span d_i
    # along their own z; links 2, 4, 6 (d = 0) carry the next motor and span
    # the start of the next segment, which runs along +y (2, 6) or -y (4).
    segments = (
        ((0, 0, 0.0), (0, 0, 0.3105), 0.6),
        ((0, 0, 0.0), (0, 0.2, 0.0), 0.4),
        ((0, 0, 0.0), (0, 0, 0.4), 0.6),
        ((0, 0, 0.0), (0, -0.2, 0.0), 0.4),
        ((0, 0, 0.0), (0, 0, 0.39), 0.6),
        ((0, 0, 0.0), (0, 0.06, 0.0), 0.5),
        ((0, 0, 0.0), (0, 0, 0.078), 0.5),
    )
    links = tuple(_link_inertia(m, a, b, f) for m, (a, b, f) in zip(masses, segments))
    return ArmDescription(
        name="kuka_lwr4plus",
        d=d,
        a=(0.0,) * 7,
        alpha=alpha,
        q_min=tuple(-v * DEG for v in lim),
        q_max=tuple(v * DEG for v in lim),
        qd_max=tuple(v * DEG for v in speeds),
        tau_max=(176.0, 176.0, 100.0, 100.0, 100.0, 38.0, 38.0),
        links=links,
    )


LWR4 = _lwr4()
