"""A simulated human teacher guiding the arm in gravity compensation.

The hand is an impedance towards a moving target (what a person's arm does
when guiding a tool): F = K_h (x_target - x) - D_h v, with a rotational
impedance keeping the tool pointing down (or turning it, for the coupler).
The target follows the task's script, with human-like variability drawn from
an explicit generator: speed (+-20 %), pressing force (N(8, 2) N, within
4-14 N), smooth path noise (an Ornstein-Uhlenbeck wander of 1.5 mm, 0.3 s),
physiological tremor (a 10 Hz resonant force of 1.5 N per axis; physiological
tremor is 8-12 Hz), and a gentle speed ramp at the start.

The teacher's ``phase`` is its script's; the true phase of every cycle is labelled
from the physics by ``robot_sim.world.labels``, in the robot, the same way in demonstrations
and reproductions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from numba import njit

from kernel_plumbing import blas
from kernel_plumbing.addresses import JIT, HoldsAddresses, address, carray_at, entry
from robot_sim.cycle import FRI_CYCLE_NS
from robot_sim.arm.description import LWR4
from robot_sim.arm.kinematics import LOG3, call_log3
from robot_sim.world.tasks import HoseCoupler, Valley

DOWN = np.diag([-1.0, 1.0, -1.0])  # tcp z pointing down, x against the base x (the READY posture)
_NORMALS_BLOCK = 3000  # the step's normal draws, a block at a time: the same numbers in the same order
_XY = np.array([1.0, 1.0, 0.0])
_Y_03 = np.array([0.0, 0.3, 0.0])


# The valley teacher's state between steps in its kernel (``ValleyTeacher._state``), by
# index: the script's time, phase and done; what it drew and its settings; then its path,
# target, path noise, tremor (two rows), the target rotation (row-major) and the wrench
(_TIME, _PHASE, _DONE, _SPEED, _PRESS, _SIDE, _GOAL_X, _TIP, _ANGLE, _GROOVE_Z, _K, _D, _ROT_K, _ROT_D,
 _PATH_NOISE, _PATH_NOISE_TIME, _RAMP_TIME, _CONTACT_THRESHOLD, _A1, _A2, _TREMOR_GAIN) = range(21)
_PATH, _TARGET, _NOISE, _TREMOR, _R_TARGET, _WRENCH, _R_ERROR, _LOG = 21, 24, 27, 30, 36, 45, 51, 60
_STATE_SIZE = 63
# what a step reads, copied in by ValleyTeacher.step: the tcp's position, velocity, rotation
# (row-major), angular velocity, and the contact force
_X, _V, _R, _W, _CONTACT = 0, 3, 6, 15, 18
_INPUT_SIZE = 21


@njit(**JIT)
def _valley_step_at(state_at, dt, inputs_at, touches_plate, noise_draw_at, tremor_draw_at, log3_fn, gemm_fn,
                    dot_fn):
    """``ValleyTeacher.step`` in one call: the script, the path noise, the hand's impedance and
    tremor, with the same operations in the same order on the same numbers; the dot
    products, the target rotation's product and its log through numpy's BLAS and
    Pinocchio's log3 (their addresses), as numpy and the bindings compute them.  Returns
    False if log3 failed."""
    s = carray_at(state_at, (_STATE_SIZE,))
    inputs = carray_at(inputs_at, (_INPUT_SIZE,))
    noise_draw, tremor_draw = carray_at(noise_draw_at, (3,)), carray_at(tremor_draw_at, (3,))
    s[_TIME] += dt
    feels = math.sqrt(blas.call_dot(dot_fn, 3, inputs_at + 8 * _CONTACT, 1, inputs_at + 8 * _CONTACT, 1)) \
        > s[_CONTACT_THRESHOLD]
    if s[_PHASE] == 0 and touches_plate and feels:
        s[_PHASE] = 1
        for i in range(3):
            s[_PATH + i] = inputs[_X + i]
    ramp = min(1.0, s[_TIME] / s[_RAMP_TIME]) if s[_RAMP_TIME] > 0 else 1.0
    speed = s[_SPEED] * ramp
    a = math.exp(-dt / s[_PATH_NOISE_TIME])
    scale = math.sqrt(1 - a * a) * s[_PATH_NOISE]
    for i in range(3):
        s[_NOISE + i] = a * s[_NOISE + i] + scale * noise_draw[i]
    if s[_PHASE] == 0:
        s[_PATH + 2] -= speed * dt
        for i in range(3):
            s[_TARGET + i] = s[_PATH + i] + s[_NOISE + i] * (1.0 if i < 2 else 0.0)
    elif s[_PHASE] == 1:
        side, angle = s[_SIDE], s[_ANGLE]
        normal = s[_LOG:_LOG + 3]  # scratch until the log: the plate's normal
        normal[0], normal[1], normal[2] = 0.0, -side * math.sin(angle), math.cos(angle)
        step = speed * dt
        s[_PATH] += step * 0.0  # numpy adds downhill's 0 too (a path at -0.0 becomes 0.0)
        s[_PATH + 1] += step * (-side * math.cos(angle))
        s[_PATH + 2] += step * -math.sin(angle)
        s[_PATH + 2] = s[_GROOVE_Z] + abs(s[_PATH + 1]) * math.tan(angle) + s[_TIP] / math.cos(angle)
        along = blas.call_dot(dot_fn, 3, state_at + 8 * _NOISE, 1, state_at + 8 * _LOG, 1)
        for i in range(3):
            lateral = s[_NOISE + i] - along * normal[i]
            s[_TARGET + i] = s[_PATH + i] + lateral - normal[i] * s[_PRESS] / s[_K]
        if side * s[_PATH + 1] <= 0.0:  # the path has reached the groove line
            s[_PHASE] = 2
            s[_PATH + 1] = 0.0
    else:
        s[_PATH] -= speed * dt
        s[_PATH + 1] = 0.0
        s[_PATH + 2] = s[_GROOVE_Z] + s[_TIP] / math.cos(s[_ANGLE])
        s[_TARGET] = s[_PATH] + 0.0 + s[_NOISE] * 0.0
        s[_TARGET + 1] = s[_PATH + 1] + 0.0 + s[_NOISE + 1] * 0.3
        s[_TARGET + 2] = s[_PATH + 2] + -s[_PRESS] / s[_K] + s[_NOISE + 2] * 0.0
        if inputs[_X] <= s[_GOAL_X]:
            s[_DONE] = 1.0
    # the hand: an impedance towards the target with tremor, and a rotational one towards R_target
    for i in range(3):
        new = s[_A1] * s[_TREMOR + i] + s[_A2] * s[_TREMOR + 3 + i] + tremor_draw[i]
        s[_TREMOR + 3 + i] = s[_TREMOR + i]
        s[_TREMOR + i] = new
        s[_WRENCH + i] = s[_K] * (s[_TARGET + i] - inputs[_X + i]) - s[_D] * inputs[_V + i] + s[_TREMOR_GAIN] * new
    blas.call_gemm(gemm_fn, np.int32(blas.ROW_MAJOR), np.int32(blas.NO_TRANS), np.int32(blas.TRANS), 3, 3, 3, 1.0,
                   state_at + 8 * _R_TARGET, 3, inputs_at + 8 * _R, 3, 0.0, state_at + 8 * _R_ERROR, 3)
    if call_log3(log3_fn, state_at + 8 * _R_ERROR, state_at + 8 * _LOG) != 0:
        return False
    for i in range(3):
        s[_WRENCH + 3 + i] = s[_ROT_K] * s[_LOG + i] - s[_ROT_D] * inputs[_W + i]
    return True


_VALLEY_STEP = entry(_valley_step_at, "int64, float64, int64, boolean, int64, int64, int64, int64, int64") \
    if LOG3 and blas.AVAILABLE else None


@dataclass(frozen=True)
class TeacherConfig:
    hand_stiffness: float = 400.0  # N/m
    hand_damping: float = 60.0  # N s/m
    hand_rot_stiffness: float = 20.0  # N m/rad
    hand_rot_damping: float = 1.5  # N m s/rad
    speed: float = 0.05  # m/s, nominal
    speed_variation: float = 0.2
    press_force: float = 8.0  # N, nominal
    press_force_std: float = 2.0
    path_noise: float = 0.0015  # m
    path_noise_time: float = 0.3  # s
    contact_threshold: float = 1.0  # N, the hand "feels" contact
    ramp_time: float = 0.3  # s
    tremor_force: float = 1.5  # N, standard deviation per axis of the hand's physiological tremor
    tremor_hz: float = 10.0  # physiological tremor: 8-12 Hz


class Teacher:
    """Base: the hand impedance, variability and bookkeeping; tasks define the script."""

    n_phases = 1

    def __init__(self, rng: np.random.Generator, config: TeacherConfig = TeacherConfig()):
        self.config = config
        self.rng = rng
        self.speed = config.speed * rng.uniform(1 - config.speed_variation, 1 + config.speed_variation)
        self.press = float(np.clip(rng.normal(config.press_force, config.press_force_std), 4.0, 14.0))
        self.phase = 0  # the script's phase
        self.done = False
        self.time = 0.0
        self._noise = np.zeros(3)
        self._wrench = np.zeros(6)
        # tremor: a resonant AR(2) process around tremor_hz, scaled to unit variance
        dt = FRI_CYCLE_NS / 1e9  # the teacher's hand is stepped once per FRI cycle
        r = math.exp(-0.3 * 2 * math.pi * config.tremor_hz * dt)
        self._a1 = 2 * r * math.cos(2 * math.pi * config.tremor_hz * dt)
        self._a2 = -r * r
        var = (1 - self._a2) / ((1 + self._a2) * ((1 - self._a2) ** 2 - self._a1**2))
        self._tremor_gain = config.tremor_force / math.sqrt(var)
        self._tremor = np.zeros((2, 3))
        self.target = None
        self.R_target = DOWN.copy()
        self._normals = np.empty(0)
        self._normals_i = 0

    def _normal3(self) -> np.ndarray:
        """The next three standard normals of ``rng``: what ``rng.normal(size=3)`` returns,
        drawn a block at a time on first use (after every draw the constructors make)."""
        i = self._normals_i
        if i + 3 > len(self._normals):
            self._normals = self.rng.normal(size=_NORMALS_BLOCK)
            i = 0
        self._normals_i = i + 3
        return self._normals[i:i + 3]

    def _advance_noise(self, dt: float) -> np.ndarray:
        c = self.config
        a = math.exp(-dt / c.path_noise_time)
        self._noise = a * self._noise + math.sqrt(1 - a * a) * c.path_noise * self._normal3()
        return self._noise

    def _ramp(self) -> float:
        return min(1.0, self.time / self.config.ramp_time) if self.config.ramp_time > 0 else 1.0

    def _advance_tremor(self) -> np.ndarray:
        new = self._a1 * self._tremor[0] + self._a2 * self._tremor[1] + self._normal3()
        self._tremor[1] = self._tremor[0]
        self._tremor[0] = new
        return self._tremor_gain * new

    def _hand(self, x, v, R, w) -> np.ndarray:
        """The hand's wrench (world axes) towards the current target, with tremor."""
        c = self.config
        out = self._wrench
        out[:3] = c.hand_stiffness * (self.target - x) - c.hand_damping * v + self._advance_tremor()
        out[3:] = c.hand_rot_stiffness * pin.log3(self.R_target @ R.T) - c.hand_rot_damping * w
        return out.copy()

    def step(self, dt, x, v, R, w, contact_force, touching) -> np.ndarray:
        """Advance by dt seconds and return the hand wrench [F; T] (world)."""
        raise NotImplementedError


class ValleyTeacher(Teacher):
    """Free motion down to one plate, slide down it to the groove, slide along the groove."""

    n_phases = 3

    def __init__(self, valley: Valley, start: np.ndarray, goal_x: float, rng: np.random.Generator,
                 config: TeacherConfig = TeacherConfig(), tip_radius: float = LWR4.tool.tip_radius):
        super().__init__(rng, config)
        self.valley = valley
        self.side = -1 if start[1] < 0 else 1
        self.goal_x = goal_x
        self.tip = tip_radius
        self.start = np.array(start, dtype=np.float64)
        self.target = self.start.copy()
        self._path = self.start.copy()  # the intended (noise-free) path point
        self._compiled = _CompiledValleyStep(self) if _VALLEY_STEP is not None else None

    def step(self, dt, x, v, R, w, contact_force, touching) -> np.ndarray:
        if self._compiled is not None:
            return self._compiled.step(dt, x, v, R, w, contact_force, touching)
        self.time += dt
        g = self.valley
        plates = {name for name in touching if name.startswith("plate")}
        feels = math.sqrt(contact_force.dot(contact_force)) > self.config.contact_threshold  # np.linalg.norm's own sum
        # the script advances on what the hand feels and where it is
        if self.phase == 0 and plates and feels:
            self.phase = 1
            self._path = x.copy()
        speed = self.speed * self._ramp()
        noise = self._advance_noise(dt)
        if self.phase == 0:
            self._path[2] -= speed * dt
            self.target = self._path + noise * _XY
        elif self.phase == 1:
            n = g.plate_normal(self.side)
            downhill = np.array([0.0, -self.side * math.cos(g.angle), -math.sin(g.angle)])
            self._path += speed * dt * downhill
            # the intended path rides on the plate, tip centre one radius off it
            self._path[2] = g.surface_z(self._path[1]) + self.tip / math.cos(g.angle)
            lateral = noise - (noise @ n) * n
            self.target = self._path + lateral - n * self.press / self.config.hand_stiffness
            if self.side * self._path[1] <= 0.0:  # the path has reached the groove line
                self.phase = 2
                self._path[1] = 0.0
        else:
            self._path[0] -= speed * dt
            self._path[1] = 0.0
            self._path[2] = g.groove_z + self.tip / math.cos(g.angle)
            self.target = self._path + np.array([0.0, 0.0, -self.press / self.config.hand_stiffness]) \
                + noise * _Y_03
            if x[0] <= self.goal_x:
                self.done = True
        return self._hand(x, v, R, w)


class _CompiledValleyStep(HoldsAddresses):
    """A valley teacher's steps through ``_valley_step_at``: its state moved into one array
    when made (the teacher's own attributes then stand still, but ``phase`` and ``done``,
    kept current), what a step reads copied into another."""

    def __init__(self, teacher: ValleyTeacher):
        self.teacher = teacher
        c, g = teacher.config, teacher.valley
        s = self.state = np.zeros(_STATE_SIZE)
        s[:_PATH] = (teacher.time, teacher.phase, teacher.done, teacher.speed, teacher.press, teacher.side,
                     teacher.goal_x, teacher.tip, g.angle, g.groove_z, c.hand_stiffness, c.hand_damping,
                     c.hand_rot_stiffness, c.hand_rot_damping, c.path_noise, c.path_noise_time, c.ramp_time,
                     c.contact_threshold, teacher._a1, teacher._a2, teacher._tremor_gain)
        s[_PATH:_PATH + 3], s[_TARGET:_TARGET + 3], s[_NOISE:_NOISE + 3] = teacher._path, teacher.target, teacher._noise
        s[_TREMOR:_TREMOR + 6] = teacher._tremor.reshape(6)
        s[_R_TARGET:_R_TARGET + 9] = teacher.R_target.reshape(9)
        self.inputs = np.zeros(_INPUT_SIZE)
        self._rotation = self.inputs[_R:_R + 9].reshape(3, 3)  # a view: R is copied in row by row
        self._state_at, self._inputs_at = address(self.state), address(self.inputs)
        # the block of normals the teacher draws from, and the one before it (a draw just before
        # the teacher made a new block must stay readable until the kernel has read it)
        self._block = self._previous = None
        self._block_at = 0

    def _draw_at(self) -> int:
        """The address of the teacher's next three normals (``Teacher._normal3``)."""
        teacher = self.teacher
        teacher._normal3()
        if teacher._normals is not self._block:
            self._previous, self._block = self._block, teacher._normals
            self._block_at = address(self._block)
        return self._block_at + 8 * (teacher._normals_i - 3)

    def step(self, dt, x, v, R, w, contact_force, touching) -> np.ndarray:
        inputs = self.inputs
        inputs[_X:_X + 3], inputs[_V:_V + 3], inputs[_W:_W + 3] = x, v, w
        self._rotation[...] = R
        inputs[_CONTACT:_CONTACT + 3] = contact_force
        touches_plate = any(name.startswith("plate") for name in touching)
        noise_at = self._draw_at()  # the step's draws in the order the script makes them
        tremor_at = self._draw_at()
        if not _VALLEY_STEP(self._state_at, dt, self._inputs_at, touches_plate, noise_at, tremor_at, LOG3, blas.GEMM,
                            blas.DOT):
            raise RuntimeError("Pinocchio's log3 failed in the teacher's hand")
        s, teacher = self.state, self.teacher
        teacher.phase, teacher.done = int(s[_PHASE]), bool(s[_DONE])
        return s[_WRENCH:_WRENCH + 6].copy()


class HoseCouplerTeacher(Teacher):
    """Approach over the coupler, enter it, press and turn the hose end a quarter turn."""

    n_phases = 2

    def __init__(self, coupler: HoseCoupler, start: np.ndarray, rng: np.random.Generator,
                 config: TeacherConfig = TeacherConfig(), tip_radius: float = LWR4.tool.tip_radius,
                 turn: float = math.pi / 2, turn_rate: float = math.radians(40.0)):
        super().__init__(rng, config)
        self.coupler = coupler
        self.tip = tip_radius
        self.start = np.array(start, dtype=np.float64)
        self.target = self.start.copy()
        self._path = self.start.copy()
        self.turn = turn
        self.turn_rate = turn_rate * rng.uniform(0.8, 1.2)
        self.turned = 0.0
        c = np.array(coupler.center)
        self._above = c + np.array([0.0, 0.0, coupler.depth + 0.03])

    def step(self, dt, x, v, R, w, contact_force, touching) -> np.ndarray:
        self.time += dt
        c = np.array(self.coupler.center)
        feels = np.linalg.norm(contact_force) > self.config.contact_threshold
        if self.phase == 0 and feels and any(t.startswith("coupler") for t in touching):
            self.phase = 1
            self._path = np.array([c[0], c[1], c[2] + self.tip])
        speed = self.speed * self._ramp()
        if self.phase == 0:
            to_above = self._above - self._path
            dist = np.linalg.norm(to_above[:2])
            if dist > 1e-3:
                # over the coupler first, at the approach height
                step = to_above / max(np.linalg.norm(to_above), 1e-9) * min(speed * dt, np.linalg.norm(to_above))
                self._path += step
            else:
                self._path[:2] = self._above[:2]
                self._path[2] -= speed * dt
            self.target = self._path + self._advance_noise(dt) * np.array([0.2, 0.2, 0.0])
        else:
            self.target = self._path + np.array([0.0, 0.0, -self.press / self.config.hand_stiffness])
            if self.turned < self.turn:
                self.turned = min(self.turn, self.turned + self.turn_rate * self._ramp() * dt)
            self.R_target = pin.exp3(np.array([0.0, 0.0, self.turned])) @ DOWN
        return self._hand(x, v, R, w)

    def rotation_done(self, R: np.ndarray, tolerance: float = math.radians(5.0)) -> bool:
        """The tool has turned (nearly) the full quarter turn about the vertical."""
        err = pin.log3(R @ (pin.exp3(np.array([0.0, 0.0, self.turn])) @ DOWN).T)
        return self.turned >= self.turn and np.linalg.norm(err) < tolerance
