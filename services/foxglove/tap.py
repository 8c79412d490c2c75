"""The visual scene fed with payloads as they cross the wire (the recorder, the live view, the export)."""

from __future__ import annotations

from services.foxglove.scene import VisualScene, world_of_scenario
from services.recordings.writer import EpisodeWriter
from services.runtime.messages import (BY_TOPIC, EPISODE_SUMMARY, ESTIMATOR_PHASE, FT_WRENCH, MessageError,
                                       ROBOT_COMMAND, ROBOT_CONTACT, ROBOT_STATE, RUNNER_EVENT, SEQ_PREFIX,
                                       SERVICE_LOG, dumps)


def encode(message: dict) -> bytes:
    """Compact JSON of a visual message, as the run's own messages are written (orjson,
    the standard library where orjson would differ; ValueError on NaN or infinity, which
    a viewer's JSON parser would refuse).  The scene at the visual rate and the world's
    geometry once a second cost the recorder more through the standard library than
    all the 1 kHz messages through orjson."""
    return dumps(message)


# only the newest counts
LATEST_TOPICS = (FT_WRENCH.topic, ESTIMATOR_PHASE.topic, ROBOT_CONTACT.topic, ROBOT_COMMAND.topic)
EVENT_TOPICS = (RUNNER_EVENT.topic, EPISODE_SUMMARY.topic, SERVICE_LOG.topic)


class VisualTap:
    """A ``VisualScene`` fed with payloads as they cross the wire, decoding only what a
    visual frame needs: the 1 kHz topics are kept undecoded and only the newest of each
    is decoded, at a visual frame (a robot state whose FRI cycle is a multiple of the
    scene's ``every``).  A payload that does not decode is counted and skipped."""

    def __init__(self, scene: VisualScene, default_model: str | None = None):
        self.scene = scene
        self._latest: dict = {}
        self.undecodable = 0
        # the model whose stiffness is drawn when an episode's start does not name one
        # (recordings from before the runner named it)
        self.default_model = default_model
        self._impedances: dict[str, list | None] = {}

    def reset(self, impedances=None) -> None:
        self._latest.clear()
        self.scene.reset(impedances)

    def _model(self, path) -> list | None:
        """The per-phase impedances of a model file (read once); None if it cannot be read."""
        if not isinstance(path, str):
            return None
        if path not in self._impedances:
            from etar.task import TaskError, load_task

            try:
                self._impedances[path] = list(load_task(path).impedances)
            except (TaskError, OSError, ValueError):
                self._impedances[path] = None
        return self._impedances[path]

    def _decode(self, topic: str, value):
        if isinstance(value, dict):
            return value
        try:
            return BY_TOPIC[topic].decode(value)
        except MessageError:
            self.undecodable += 1
            return None

    def take(self, topic: str, raw: bytes, message: dict | None = None) -> list[tuple[str, dict]]:
        """The visual messages this payload (of run topic ``topic``) brings; ``message``: the
        payload already decoded, where the transport has it."""
        if topic in LATEST_TOPICS:
            self._latest[topic] = raw if message is None else message
            return []
        if topic in EVENT_TOPICS:
            msg = self._decode(topic, raw if message is None else message)
            if msg is None:
                return []
            if topic == RUNNER_EVENT.topic and msg["event"] == "episode_begin":
                # a reproduction's start names its model: the stiffness its commands apply
                self.reset(self._model(msg["info"].get("model") or self.default_model))
            return self.scene.take(topic, msg)
        if topic != ROBOT_STATE.topic:
            return []
        if message is None:
            m = SEQ_PREFIX.match(raw)
            if m is None or int(m.group(1)) % self.scene.every:
                return []
        elif message["seq"] % self.scene.every:
            return []
        state = self._decode(topic, raw if message is None else message)
        if state is None:
            return []
        out = []
        for t, value in self._latest.items():
            msg = self._decode(t, value)
            if msg is not None:
                out += self.scene.take(t, msg)
        self._latest.clear()
        return out + self.scene.take(ROBOT_STATE.topic, state)


class VisualRecordings:
    """Opens an episode's recording that carries, beside the run's own messages, the visual
    topics they bring (``/viz/...`` at ``rate_hz``; none at 0 or where the scenario names no
    world): what the recorder writes.  Called as ``EpisodeWriter`` is, so that the writer's
    helper process (``services.recordings.offload``) can open them: in an in-process run
    drawing the scene then costs the run's one CPU nothing.  Keeps one tap per world: the
    arm's kinematics and the world's geometry are built once."""

    def __init__(self, rate_hz: float):
        self.rate_hz = rate_hz
        self._taps: dict[str, VisualTap] = {}

    def __call__(self, path, **options) -> "VisualRecording":
        return VisualRecording(EpisodeWriter(path, **options), self._tap_for(options.get("scenario_text")))

    def _tap_for(self, scenario_text: str | None) -> VisualTap | None:
        if not self.rate_hz or not scenario_text:
            return None
        try:
            world = world_of_scenario(scenario_text)
        except ValueError:
            return None
        if world not in self._taps:
            try:
                self._taps[world] = VisualTap(VisualScene(world, self.rate_hz))
            except ValueError:
                return None
        tap = self._taps[world]
        tap.reset()
        return tap


class VisualRecording:
    """One episode's ``EpisodeWriter`` and the visual messages its samples bring, recorded
    after each at its reception time.  They are a view of the run: whatever goes wrong
    drawing them costs only them (counted in ``visual_errors``, payloads the tap could not
    decode in ``visual_undecodable``), never a message of the run."""

    def __init__(self, writer: EpisodeWriter, tap: VisualTap | None):
        self.writer = writer
        self.tap = tap
        self._undecodable0 = 0 if tap is None else tap.undecodable
        self.visual_errors = 0

    @property
    def path(self):
        return self.writer.path

    @property
    def messages_written(self) -> int:
        return self.writer.messages_written

    @property
    def bad_payloads(self) -> int:
        return self.writer.bad_payloads

    @property
    def visual_undecodable(self) -> int:
        return 0 if self.tap is None else self.tap.undecodable - self._undecodable0

    @property
    def finished(self) -> bool:
        return self.writer.finished

    def add(self, key_expr: str, payload: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        self.writer.add(key_expr, payload, log_time_ns, publish_time_ns)
        if self.tap is None:
            return
        try:
            visuals = self.tap.take(key_expr[len(self.writer.prefix):], payload)
        except Exception:  # noqa: BLE001 - counted; the run's own messages go on
            self.visual_errors += 1
            return
        for visual_topic, visual in visuals:
            try:  # one that will not encode (a NaN) costs only itself
                data = encode(visual)
            except ValueError:
                self.visual_errors += 1
                continue
            self.writer.add(visual_topic, data, log_time_ns, log_time_ns)

    def finish(self) -> None:
        self.writer.finish()
