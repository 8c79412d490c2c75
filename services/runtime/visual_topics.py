"""The visual topics a recording carries beside the run's own (drawn by ``services.foxglove``):
their names, their schemas (Foxglove's well-known ones, and ``etar.VisualStatus``)
and their rate.  Here, below both the recorder's file format and the Foxglove wing,
because the writer registers their channels and the export writes them.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

from robot_sim.cycle import FRI_RATE_HZ

SCHEMA_DIR = Path(__file__).with_name("foxglove_schemas")  # from @foxglove/schemas 2.1.0 (MIT), unchanged
VISUAL_RATE_HZ = 50.0  # visual frames per second of simulated time: one in every 20 FRI cycles
MAX_VISUAL_RATE_HZ = float(FRI_RATE_HZ)  # a frame every FRI cycle at most
FOXGLOVE_PORT = 8765  # Foxglove's own default for a live view's WebSocket
TOPIC_TF = "/viz/tf"
TOPIC_SCENE = "/viz/scene"
TOPIC_GEOMETRY = "/viz/geometry"
TOPIC_STATUS = "/viz/status"
TOPIC_LOG = "/viz/log"
# topic -> schema name; a foxglove.* name is what makes Foxglove recognise the schema
SCHEMA_NAMES = {TOPIC_TF: "foxglove.FrameTransforms", TOPIC_GEOMETRY: "foxglove.SceneUpdate",
                TOPIC_SCENE: "foxglove.SceneUpdate",
                TOPIC_STATUS: "etar.VisualStatus", TOPIC_LOG: "foxglove.Log"}


def check_visual_rate(rate_hz: float, name: str = "visual rate", none: bool = False) -> float:
    """``rate_hz`` if it is a visual rate (0 too with ``none``: no visual topics); ValueError naming ``name``."""
    if (none and rate_hz == 0) or 0 < rate_hz <= MAX_VISUAL_RATE_HZ:
        return rate_hz
    raise ValueError(f"{name} must be {'0 (none) or ' if none else ''}in (0, {MAX_VISUAL_RATE_HZ:g}] Hz "
                     f"(a frame every FRI cycle at most), got {rate_hz}")


# the channel metadata that marks a visual topic as derived by the recorder, not received
# (the value recordings have carried since the visual topics came: readers still rely on it)
DERIVED_BY = "services.visual"

STATUS_SCHEMA = {
    "title": "etar.VisualStatus",
    "description": "The run's state at the visual rate, for plots and state transitions (services.foxglove.scene)",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "title": "time", "description": "simulation time",
                      "properties": {"sec": {"type": "integer", "minimum": 0},
                                     "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}},
        "seq": {"type": "integer", "description": "FRI cycle"},
        "episode": {"type": "integer"},
        "force": {"type": "array", "items": {"type": "number"}, "description": "measured force, sensor frame, N"},
        "torque": {"type": "array", "items": {"type": "number"}, "description": "measured torque, sensor frame, N m"},
        "force_norm": {"type": "number", "description": "|measured force|, N"},
        "phase": {"type": "integer", "description": "estimated phase (-1: none yet)"},
        "true_phase": {"type": "integer", "description": "the physics' phase label"},
        "posterior": {"type": "array", "items": {"type": "number"}, "description": "p(phase | inputs so far)"},
        "stiffness": {"type": "array", "items": {"type": "number"},
                      "description": "principal translational stiffnesses the commander applies, N/m, largest "
                                     "first (empty: no command yet, or the phase's impedance is unknown)"},
        "applied_phase": {"type": "integer", "description": "phase whose law the command applies (-1: holding)"},
        "hold": {"type": "string", "description": "why the commander holds ('' : it does not)"},
        "fri_quality": {"type": "integer", "description": "0 UNACCEPTABLE, 1 BAD, 2 OK, 3 PERFECT"},
        "fri_state": {"type": "integer", "description": "0 OFF, 1 MON, 2 CMD"},
        "tcp": {"type": "array", "items": {"type": "number"}, "description": "measured tcp position, base frame, m"},
    },
}



@lru_cache(maxsize=None)
def schema_bytes(topic: str) -> bytes:
    """The JSON Schema a visual topic's channel carries in MCAP and over the WebSocket."""
    name = SCHEMA_NAMES[topic]
    if name.startswith("foxglove."):
        return (SCHEMA_DIR / f"{name.split('.', 1)[1]}.json").read_bytes()
    return json.dumps(STATUS_SCHEMA).encode()

