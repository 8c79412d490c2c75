"""What Foxglove draws of a run: the arm, the task world, the wrench, the commanded
stiffness and the phase, as Foxglove's well-known schemas (JSON encoded).

``VisualScene`` turns the run's own messages into visual messages at a visual
rate (50 Hz by default: one in every 20 FRI cycles):

- ``/viz/tf`` (``foxglove.FrameTransforms``): every link frame and the tcp in
  ``base``, from the measured joint positions through the KRC's kinematic model
  (Pinocchio, ``robot_sim.arm.kinematics``: the one URDF both simulator and KRC use);
- ``/viz/geometry`` (``foxglove.SceneUpdate``): the arm's links and the task world
  (plates and groove, or coupler) as the MuJoCo model the physics runs has them,
  each arm geom attached to its link's frame, sent at the first visual frame and
  once a second, on a topic of their own: a player that seeks restores the last
  message of each topic before that time, which on this topic always holds them
  (mixed into the overlays' topic, they were in one message of fifty, and a seek
  lost the arm and the world);
- ``/viz/scene`` (``foxglove.SceneUpdate``): the overlays at the visual rate:
  the measured force as an arrow from the tcp (the contact), the translational
  stiffness the commander applies as an ellipsoid at the tcp (its axes the stiffness' principal
  axes, in proportion: the learned K = R V R^T of the phase whose law the command
  names, from the episode's model, or the hold stiffness while it holds), the
  estimated and the true phase as the ellipsoid's colour and a text over the tcp;
  the arm drawn see-through, so that the wrist hides none of them;
- ``/viz/status`` (``etar.VisualStatus``, a JSON Schema of our own): the same
  figures as plain numbers for Foxglove's plots and state-transition panels;
- ``/viz/log`` (``foxglove.Log``): the services' log lines (``service/log``), the
  runner's stage and episode events, the episode summaries and the commander's
  holds, as log lines.

Inner timestamps are simulation time (``stamp_ns``), so transforms and entities
agree with each other whatever the transport; the caller chooses the log time.
Pure: no messaging and no files; the recorder, ``etar-bench export --foxglove``
and the live view (``services.nodes.foxglove_bridge``) all drive this one object;
``services.foxglove.tap`` feeds it payloads as they cross the wire.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from robot_sim.cycle import FRI_RATE_HZ
from services.runtime.visual_topics import (TOPIC_GEOMETRY, TOPIC_LOG, TOPIC_SCENE, TOPIC_STATUS, TOPIC_TF,
                                            VISUAL_RATE_HZ, check_visual_rate)
from services.runtime.messages import (EPISODE_SUMMARY, ESTIMATOR_PHASE, FT_WRENCH, ROBOT_COMMAND,
                                       ROBOT_CONTACT, ROBOT_STATE, RUNNER_EVENT, SERVICE_LOG)

FRAMES = ("link1", "link2", "link3", "link4", "link5", "link6", "link7", "flange", "ati_sensor", "tool", "tcp")
ARROW_M_PER_N = 0.01  # the force arrow: 1 cm per newton, at most MAX_ARROW_M
MAX_ARROW_M = 0.4
ELLIPSOID_M_PER_N_M = 0.06 / 2000.0  # the stiffness ellipsoid: 6 cm across at the hold stiffness 2000 N/m
MIN_ELLIPSOID_M = 0.004
# the force arrow is yellow, which no phase and none of a frame's red-green-blue axes is
FORCE_COLOUR = (1.0, 0.9, 0.0)
PHASE_COLOURS = ((0.2, 0.6, 1.0), (1.0, 0.55, 0.1), (0.2, 0.8, 0.3), (0.85, 0.25, 0.8), (0.6, 0.45, 1.0),
                 (0.3, 0.9, 0.9))
# the arm see-through: the force arrow and the ellipsoid are inside the sensor and the
# tool, and from most views the wrist stands between the viewer and the text
ARM_ALPHA = 0.6
PHASE_TEXT_ABOVE_TCP_M = 0.2  # over the plates: the viewer hides a text behind what stands in front
NO_PHASE = (0.6, 0.6, 0.6)
LOG_INFO, LOG_WARNING = 2, 3

def world_of_scenario(text) -> str:
    """The ``world`` a scenario's text (a recording's attachment, a runner's begin_episode)
    names; ValueError saying what is wrong otherwise."""
    import yaml

    try:
        data = yaml.safe_load(text.decode("utf-8") if isinstance(text, bytes) else text)
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ValueError(f"not a scenario ({exc})") from None
    world = data.get("world") if isinstance(data, dict) else None
    if not isinstance(world, str):
        raise ValueError(f"field 'world' is {world!r}, not a name")
    return world


def time_of(ns: int) -> dict:
    ns = max(int(ns), 0)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _quaternion(w, x, y, z) -> dict:
    return {"x": float(x), "y": float(y), "z": float(z), "w": float(w)}


def _orientation(q) -> dict:
    """A Foxglove quaternion of a Pinocchio (Eigen) one."""
    return _quaternion(q.w, q.x, q.y, q.z)


def _quat_of_matrix(R: np.ndarray) -> dict:
    import pinocchio as pin

    return _orientation(pin.Quaternion(np.asarray(R, dtype=np.float64)))


_X = np.array([1.0, 0.0, 0.0])


def _x_onto(v: np.ndarray) -> dict:
    """The rotation taking +x onto the direction of ``v`` (Foxglove's arrows point along +x)."""
    import pinocchio as pin

    return _orientation(pin.Quaternion.FromTwoVectors(_X, np.asarray(v, dtype=np.float64)))


def _colour(rgb, a: float = 1.0) -> dict:
    return {"r": float(rgb[0]), "g": float(rgb[1]), "b": float(rgb[2]), "a": float(a)}


def phase_colour(phase: int | None):
    return NO_PHASE if phase is None or phase < 0 else PHASE_COLOURS[phase % len(PHASE_COLOURS)]


def _pose(position, orientation: dict) -> dict:
    return {"position": {"x": float(position[0]), "y": float(position[1]), "z": float(position[2])},
            "orientation": orientation}


def _entity(stamp_ns: int, frame_id: str, entity_id: str, **primitives) -> dict:
    """A SceneEntity: every primitive list present (the schema requires them all)."""
    e = {"timestamp": time_of(stamp_ns), "frame_id": frame_id, "id": entity_id, "lifetime": {"sec": 0, "nsec": 0},
         "frame_locked": True, "metadata": [], "arrows": [], "cubes": [], "spheres": [], "cylinders": [],
         "lines": [], "triangles": [], "texts": [], "models": []}
    e.update(primitives)
    return e


# Foxglove's primitive for each of the world's shapes
PRIMITIVES = {"box": "cubes", "sphere": "spheres", "cylinder": "cylinders"}


@lru_cache(maxsize=None)
def world_geometry(world: str) -> tuple:
    """(frame_id, primitive, pose, size, rgba) of every geom the physics has
    (``robot_sim.world.geometry``): the task's on ``base``, the arm's on the frame of
    their link."""
    from robot_sim.world.geometry import world_geoms

    return tuple((g.frame, PRIMITIVES[g.shape], _pose(g.position, _quaternion(*g.quaternion)), g.size, g.rgba)
                 for g in world_geoms(world))


class VisualScene:
    """The visual messages of one episode; ``take`` every message of the run (decoded),
    ``events`` for the log lines.  ``reset`` between episodes."""

    def __init__(self, world: str, rate_hz: float = VISUAL_RATE_HZ):
        from robot_sim.arm.kinematics import ArmKinematics

        check_visual_rate(rate_hz)
        self.world = world
        self.every = max(1, round(FRI_RATE_HZ / rate_hz))
        self.kinematics = ArmKinematics()
        self._frame_ids = [self.kinematics.model.getFrameId(name) for name in FRAMES]
        self.geometry = world_geometry(world)
        self.reset()

    def reset(self, impedances=None) -> None:
        """A new episode; ``impedances``: its model's per-phase impedances (``etar.task.
        LearnedTask.impedances``), for the stiffness the commands apply."""
        self._stiffness = [None if imp is None else np.asarray(imp.stiffness, dtype=np.float64)
                           for imp in (impedances or [])]
        self._known = impedances is not None
        self._wrench = None
        self._estimate = None
        self._true_phase = -1
        self._command = None
        self._hold = ""
        self._static_at = None  # FRI cycle the static scene was last sent
        self._stamp = 0  # simulation time of the newest visual frame

    # ------------------------------------------------------------------ messages

    def take(self, topic: str, msg: dict) -> list[tuple[str, dict]]:
        """The visual messages ``msg`` (of run topic ``topic``, e.g. ``robot/state``) brings:
        none, or at the visual rate's cycles the transforms, the scene and the status."""
        if topic == FT_WRENCH.topic:
            self._wrench = msg["wrench"]
        elif topic == ESTIMATOR_PHASE.topic:
            self._estimate = msg
        elif topic == ROBOT_CONTACT.topic:
            self._true_phase = int(msg["true_phase"])
        elif topic == ROBOT_COMMAND.topic:
            self._command = msg
            if msg["hold"] != self._hold:
                was, self._hold = self._hold, msg["hold"]
                text = f"commander holds the arm: {msg['hold']}" if msg["hold"] else f"commander resumes after {was}"
                return [(TOPIC_LOG, self.log_line(msg["stamp_ns"], text, "impedance_commander",
                                                  LOG_WARNING if msg["hold"] else LOG_INFO))]
        elif topic == EPISODE_SUMMARY.topic:
            return [(TOPIC_LOG, self.log_line(msg["stamp_ns"], f"{msg['kind']} {msg['episode']} ended: "
                                              f"{msg['reason']}, peak contact {msg['peak_contact_force']:.1f} N",
                                              "robot", LOG_INFO))]
        elif topic == SERVICE_LOG.topic:
            # a service's line has no simulation time: it sits where the run is now
            level = msg["level"] if msg["level"] in (1, 2, 3, 4, 5) else LOG_INFO
            return [(TOPIC_LOG, self.log_line(self._stamp, msg["text"], msg["role"], level))]
        elif topic == RUNNER_EVENT.topic:
            what = " ".join(str(x) for x in (msg["event"], msg["stage"], msg["episode"] if msg["episode"] >= 0
                                             else "") if x != "")
            return [(TOPIC_LOG, self.log_line(msg["stamp_ns"], what, "runner", LOG_INFO))]
        elif topic == ROBOT_STATE.topic and msg["seq"] % self.every == 0:
            return self._frame(msg)
        return []

    def log_line(self, stamp_ns: int, message: str, name: str, level: int = LOG_INFO) -> dict:
        return {"timestamp": time_of(stamp_ns), "level": level, "message": message, "name": name,
                "file": "", "line": 0}

    def _frame(self, state: dict) -> list[tuple[str, dict]]:
        stamp = self._stamp = state["stamp_ns"]
        q = np.asarray(state["msr_jnt_pos"], dtype=np.float64)
        kin = self.kinematics
        kin.update_frames(q)
        transforms = []
        for name, fid in zip(FRAMES, self._frame_ids):
            placement = kin.data.oMf[fid]
            t = placement.translation
            transforms.append({"timestamp": time_of(stamp), "parent_frame_id": "base", "child_frame_id": name,
                               "translation": {"x": float(t[0]), "y": float(t[1]), "z": float(t[2])},
                               "rotation": _quat_of_matrix(placement.rotation)})
        out = [(TOPIC_TF, {"transforms": transforms})]
        tcp = kin.data.oMf[self._frame_ids[-1]].translation
        sensor_rotation = kin.data.oMf[self._frame_ids[FRAMES.index("ati_sensor")]].rotation
        principal = self._principal_stiffness()
        seq = state["seq"]
        if self._static_at is None or seq - self._static_at >= FRI_RATE_HZ or seq < self._static_at:
            self._static_at = seq
            out.append((TOPIC_GEOMETRY, {"deletions": [], "entities": self._static(stamp)}))
        out.append((TOPIC_SCENE, {"deletions": [], "entities": self._overlay(stamp, tcp, principal,
                                                                              sensor_rotation)}))
        out.append((TOPIC_STATUS, self._status(state, tcp, principal)))
        return out

    def _static(self, stamp: int) -> list[dict]:
        by_frame: dict[str, dict] = {}
        for frame, prim, pose, dims, rgba in self.geometry:
            e = by_frame.setdefault(frame, _entity(stamp, frame, f"geometry/{frame}"))
            alpha = rgba[3] if frame == "base" else min(rgba[3], ARM_ALPHA)
            e[prim].append({"pose": pose, "size": {"x": dims[0], "y": dims[1], "z": dims[2]},
                            "color": _colour(rgba[:3], alpha),
                            **({"bottom_scale": 1.0, "top_scale": 1.0} if prim == "cylinders" else {})})
        return list(by_frame.values())

    def applied_stiffness(self) -> np.ndarray | None:
        """(3, 3) translational stiffness of the last command's law, N/m; None if unknown."""
        if self._command is None:
            return None
        applied = int(self._command["phase"])
        if applied < 0:
            from etar.policy import HOLD_STIFFNESS

            return HOLD_STIFFNESS * np.eye(3)
        if not self._known or applied >= len(self._stiffness):
            return None
        return self._stiffness[applied]

    def _principal_stiffness(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(principal stiffnesses ascending (3,), their axes as a right-handed rotation) of
        ``applied_stiffness``; None if unknown."""
        K = self.applied_stiffness()
        if K is None:
            return None
        w, V = np.linalg.eigh(0.5 * (K + K.T))
        if np.linalg.det(V) < 0:
            V[:, 2] = -V[:, 2]
        return w, V

    def _overlay(self, stamp: int, tcp, principal, sensor_rotation) -> list[dict]:
        """The wrench arrow, the stiffness ellipsoid and the phase text, on the tcp side."""
        phase = None if self._estimate is None else int(self._estimate["phase"])
        colour = phase_colour(phase)
        prims = {"arrows": [], "texts": []}
        if self._wrench is not None:
            # measured in the sensor's axes, drawn in base's from the contact (the tcp)
            f = sensor_rotation @ np.asarray(self._wrench[:3], dtype=np.float64)
            length = min(float(np.linalg.norm(f)) * ARROW_M_PER_N, MAX_ARROW_M)
            if length > 1e-4:
                prims["arrows"].append({"pose": _pose(tcp, _x_onto(f)), "shaft_length": length * 0.75,
                                        "shaft_diameter": 0.012, "head_length": length * 0.25,
                                        "head_diameter": 0.032, "color": _colour(FORCE_COLOUR)})
        ellipsoid = []
        if principal is not None:
            # the principal axes as the ellipsoid's axes, in base axes at the tcp
            w, V = principal
            k = np.maximum(w * ELLIPSOID_M_PER_N_M, MIN_ELLIPSOID_M)
            ellipsoid.append({"pose": _pose(tcp, _quat_of_matrix(V)),
                              "size": {"x": float(k[0]), "y": float(k[1]), "z": float(k[2])},
                              "color": _colour(colour, 0.35)})
        label = "phase -" if phase is None else f"phase {phase}"
        label += f" (true {self._true_phase})" + (f" HOLD {self._hold}" if self._hold else "")
        above = np.asarray(tcp, dtype=np.float64) + (0.0, 0.0, PHASE_TEXT_ABOVE_TCP_M)  # up in base, not along the tool
        prims["texts"].append({"pose": _pose(above, _quaternion(1, 0, 0, 0)),
                               "billboard": True, "font_size": 18.0, "scale_invariant": True, "color": _colour(colour), "text": label})
        # in base: the arrow and the ellipsoid at the tcp, the text above it
        return [_entity(stamp, "base", "overlay/wrench", arrows=prims["arrows"]),
                _entity(stamp, "base", "overlay/tcp", texts=prims["texts"]),
                _entity(stamp, "base", "overlay/stiffness", spheres=ellipsoid)]

    def _status(self, state: dict, tcp, principal) -> dict:
        w = [0.0] * 6 if self._wrench is None else [float(x) for x in self._wrench]
        est = self._estimate
        return {"timestamp": time_of(state["stamp_ns"]), "seq": int(state["seq"]), "episode": int(state["episode"]),
                "force": w[:3], "torque": w[3:], "force_norm": float(np.linalg.norm(w[:3])),
                "phase": -1 if est is None else int(est["phase"]), "true_phase": self._true_phase,
                "posterior": [] if est is None else [float(p) for p in est["posterior"]],
                "stiffness": [] if principal is None else [float(k) for k in principal[0][::-1]],
                "applied_phase": -1 if self._command is None else int(self._command["phase"]),
                "hold": self._hold, "fri_quality": int(state["fri_quality"]), "fri_state": int(state["fri_state"]),
                "tcp": [float(x) for x in tcp]}


