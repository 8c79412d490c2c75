"""The visual scene fed with payloads as they cross the wire (the recorder, the live view, the export)."""

from __future__ import annotations

from services.foxglove.scene import VisualScene
from services.runtime.messages import BY_TOPIC, SEQ_PREFIX, MessageError, dumps


def encode(message: dict) -> bytes:
    """Compact JSON of a visual message, as the run's own messages are written (orjson,
    the standard library where orjson would differ; ValueError on NaN or infinity, which
    a viewer's JSON parser would refuse).  The scene at the visual rate and the world's
    geometry once a second cost the recorder more through the standard library than
    all the 1 kHz messages through orjson."""
    return dumps(message)


LATEST_TOPICS = ("ft/wrench", "estimator/phase", "robot/contact", "robot/command")  # only the newest counts
EVENT_TOPICS = ("runner/event", "robot/episode", "service/log")


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
            if topic == "runner/event" and msg["event"] == "episode_begin":
                # a reproduction's start names its model: the stiffness its commands apply
                self.reset(self._model(msg["info"].get("model") or self.default_model))
            return self.scene.take(topic, msg)
        if topic != "robot/state":
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
        return out + self.scene.take("robot/state", state)
