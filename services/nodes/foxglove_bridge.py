"""The Foxglove bridge node: the run's visual topics live over Foxglove's WebSocket protocol.

Takes every message of the run undecoded, as the recorder does, turns them into
the visual topics exactly as the recorder does (``services.foxglove.tap``: the
live view shows what the recording holds), and logs them to channels of a
Foxglove SDK server (``foxglove-sdk``): connect Foxglove to ``ws://HOST:PORT``
(``--host``, ``--port``).  It publishes nothing on the run's bus and answers no
cycle, so it cannot change what is recorded or what the cell does; a slow viewer
only loses visual messages (the SDK drops the oldest of a client's queue).

The channels carry JSON with Foxglove's JSON Schemas (the recording's encoding).
The SDK's server listens on loopback behind ``services.foxglove.door``: it speaks
``foxglove.sdk.v1`` only, and the door lets in, under that name, a viewer that offers
only ``foxglove.websocket.v1`` (Foxglove Studio 1.48, the last open-source release;
Lichtblick until December 2025) -- the same wire format under its older name.
"""

from __future__ import annotations

import errno
import json
import threading
from dataclasses import dataclass

from robot_sim.world.tasks import TASK_WORLDS
from services.runtime import topics
from services.runtime.bus import Node, Subscription
from services.runtime.config import option
from services.runtime.visual_topics import FOXGLOVE_PORT, SCHEMA_NAMES, VISUAL_RATE_HZ, check_visual_rate, schema_bytes
from services.foxglove.door import SubprotocolDoor
from services.foxglove.scene import VisualScene
from services.foxglove.tap import VisualTap, encode



@dataclass(frozen=True)
class FoxgloveBridgeConfig:
    world: str = option("valley", "the task world whose geometry is drawn", choices=TASK_WORLDS)
    host: str = option("127.0.0.1", "address the WebSocket server listens on", metavar="ADDR")
    port: int = option(FOXGLOVE_PORT, "port of the WebSocket server, 0..65535 (0: any free one, said in status)",
                       metavar="PORT")
    visual_rate_hz: float = option(VISUAL_RATE_HZ, "rate of the visual topics sent to Foxglove, Hz, at most one "
                                                   "per FRI cycle (1000)", metavar="HZ")

    def __post_init__(self):
        if not (0 <= self.port <= 65535):
            raise ValueError(f"port must be in 0..65535, got {self.port}")
        check_visual_rate(self.visual_rate_hz, "visual_rate_hz")


class FoxgloveBridgeNode(Node):
    name = "foxglove_bridge"

    def __init__(self, config: FoxgloveBridgeConfig, bus, clock, *, run_id: str, mode: str = "lockstep", **_):
        import foxglove

        super().__init__(bus, clock)
        self.run_id = topics.check_run_id(run_id)
        self.tap = VisualTap(VisualScene(config.world, config.visual_rate_hz))
        self.lock = threading.Lock()  # Zenoh may call back from more than one thread
        self.sent = 0
        self.errors = 0
        try:
            # the SDK's server, reached through the door only
            self.server = foxglove.start_server(name=f"etar {run_id}", host="127.0.0.1", port=0)
        except RuntimeError as exc:  # the SDK's FoxgloveError
            raise OSError(f"the live view's server did not start: {exc}") from None
        try:
            self.door = SubprotocolDoor(config.host, config.port, self.server.port)
        except OSError as exc:
            self.server.stop()
            # the port's flag differs by command (etar-bench run --foxglove PORT, this node's --port)
            hint = "; another port, or 0 for any free one" if exc.errno == errno.EADDRINUSE else ""
            raise OSError(f"the live view cannot listen on {config.host}:{config.port}: {exc.strerror or exc}"
                          f"{hint}") from None
        self.port = self.door.port
        self.channels = {topic: foxglove.Channel(topic, schema=json.loads(schema_bytes(topic)),
                                                 message_encoding="json")
                         for topic in SCHEMA_NAMES}
        self.subscriptions = [Subscription("**", self.on_sample, decode=False)]

    def on_sample(self, topic: str, recv_ns: int, raw: bytes, message: dict | None = None) -> None:
        try:
            with self.lock:
                visuals = self.tap.take(topic, raw, message)  # an episode's start resets the tap
            for visual_topic, visual in visuals:
                self.channels[visual_topic].log(encode(visual), log_time=recv_ns)
                self.sent += 1
        except Exception:  # noqa: BLE001 - a view of the run: counted, never the run's problem
            self.errors += 1

    def status(self) -> dict:
        return {"port": self.port, "sent": self.sent, "errors": self.errors, "undecodable": self.tap.undecodable,
                "viewers_by_old_name": self.door.renamed}

    def close(self) -> None:
        self.door.close()
        self.server.stop()
