"""``etar-bench export RUN_DIR --foxglove``: the visual topics added to recordings made
without them (before they existed, or with the recorder's ``--visual-rate-hz 0``).

Each recording of the run is read, its own messages fed through the recorder's
``services.foxglove.tap.VisualTap`` in the order the recorder received them (log
time), and the file written again with the visual topics beside (the world from
the scenario the recording carries).  Every original message stays byte for byte
(``services.recordings.recovery.write_copy`` reads the new file back and compares before it
replaces the old one).  A recording that already has them, or that is
truncated (``etar-bench recover`` it first), is left as it is and said why.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from services.recordings.format import SCENARIO_ATTACHMENT, RecordingError
from services.recordings.reader import read_episode
from services.recordings.recovery import write_copy
from services.runtime.visual_topics import SCHEMA_NAMES, VISUAL_RATE_HZ, schema_bytes
from services.foxglove.scene import VisualScene, world_of_scenario
from services.foxglove.tap import VisualTap, encode


@dataclass(frozen=True)
class Exported:
    path: Path
    added: int  # visual messages written; 0: left as it was
    why: str  # what was done, or why not

    def describe(self) -> str:
        return f"{self.path}: {self.why}"


def world_of_episode(episode, path: Path) -> str:
    """The world a recorded episode ran in, from the scenario it carries; RecordingError
    naming the file and the attachment otherwise."""
    text = episode.attachments.get(SCENARIO_ATTACHMENT)
    if text is None:
        raise RecordingError(f"{path}: no {SCENARIO_ATTACHMENT!r} attachment: the world it ran in is unknown")
    try:
        return world_of_scenario(text)
    except ValueError as exc:
        raise RecordingError(f"{path}: attachment {SCENARIO_ATTACHMENT!r}: {exc}") from None


def add_visual_topics(path, rate_hz: float = VISUAL_RATE_HZ, scenes: dict | None = None) -> Exported:
    path = Path(path)
    episode = read_episode(path)
    if any(topic in SCHEMA_NAMES for topic in episode.channels):
        return Exported(path, 0, "has the visual topics already: left as it is")
    if not episode.complete:
        return Exported(path, 0, f"truncated ({episode.problem}): left as it is; `etar-bench recover` it first")
    world = world_of_episode(episode, path)
    scenes = {} if scenes is None else scenes
    if (world, rate_hz) not in scenes:
        scenes[world, rate_hz] = VisualScene(world, rate_hz)
    # a recording from before the episode's start named its model: the run's own model
    model = episode.metadata.get("model") or (str(path.parent.parent / "model.json")
                                              if (path.parent.parent / "model.json").exists() else None)
    tap = VisualTap(scenes[world, rate_hz], default_model=model)
    tap.reset()
    extra = []
    unencodable = 0
    for m in episode.messages:
        for topic, visual in tap.take(m.topic.lstrip("/"), m.payload):
            try:
                extra.append((topic, SCHEMA_NAMES[topic], schema_bytes(topic), m.log_time_ns, encode(visual)))
            except ValueError:  # a NaN, which no viewer's JSON parser reads: left out, counted
                unencodable += 1
    write_copy(episode, path, library=f"{episode.library}; visual topics by etar-bench export",
               metadata=dict(episode.metadata, visual_topics_added_by="etar-bench export --foxglove"),
               extra=extra, what="exported")
    notes = f", {tap.undecodable} undecodable message(s) skipped" if tap.undecodable else ""
    if unencodable:
        notes += f", {unencodable} visual message(s) with a non-finite value left out"
    return Exported(path, len(extra), f"added {len(extra)} visual messages ({world}, {rate_hz:g} Hz){notes}")


def export_foxglove(run_dir, rate_hz: float = VISUAL_RATE_HZ, progress=None) -> list[Exported]:
    """``add_visual_topics`` for every recording of the run in ``run_dir``."""
    run_dir = Path(run_dir)
    folder = run_dir / "recordings"
    if not folder.is_dir():
        raise RecordingError(f"{run_dir}: no recordings/ folder: not a run's output folder")
    paths = sorted(p for p in folder.glob("*.mcap"))
    if not paths:
        raise RecordingError(f"{folder}: no .mcap recordings")
    scenes: dict = {}
    out = []
    for path in paths:
        result = add_visual_topics(path, rate_hz, scenes)
        out.append(result)
        if progress is not None:
            progress(result.describe())
    return out
