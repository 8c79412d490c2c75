"""Recovering a truncated or damaged recording: every complete chunk before the end or the
damage, written out as a finished MCAP file.

A recorder killed mid-episode leaves a file without its footer and summary:
``read_episode`` reads what it kept (the metadata, the scenario, every chunk
that was completely written) but a seeking reader (Foxglove, ``mcap info``,
``make_reader``) cannot open it.  ``recover`` writes those records again as a
finished file beside the original (which it leaves as it is): the same
channels, schemas, metadata (plus what was lost, under ``recovered``), the
scenario attachment, and every recovered message with its log and publish
times and its payload byte for byte.  The new file is read back and compared
before ``recover`` says it is done.  A finished file damaged inside (a chunk
that fails its CRC or does not decompress, a damaged summary), which every
other reader refuses, gives the chunks before the damage the same way.  A
finished recording among the files given is said and left as it is (no
failure: the exit status is 1 only when a file could not be recovered).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType, IndexType, Writer

from services.recordings.format import CHUNK_SIZE, METADATA_NAME, SCENARIO_ATTACHMENT, SCENARIO_MEDIA_TYPE, RecordingError
from services.recordings.reader import read_episode
from services.runtime.messages import ROBOT_STATE, loads
from services.runtime.visual_topics import DERIVED_BY


@dataclass(frozen=True)
class Recovered:
    source: Path
    path: Path
    messages: int
    chunks: int  # complete chunks the truncated file held
    last_robot_seq: int | None  # the last robot cycle whose state was kept
    problem: str

    def describe(self) -> str:
        seq = "" if self.last_robot_seq is None else f", robot cycles up to {self.last_robot_seq}"
        # a damaged file: the reader's own account of what was read and what was lost
        lost = (self.problem if self.problem.startswith("corrupt") else
                f"lost: what the recorder had not yet written as a whole chunk (at most {CHUNK_SIZE // 1024} KiB of "
                "messages, about 100 ms of an episode)")
        return (f"{self.source}: recovered {self.messages} messages from {self.chunks} complete chunk(s){seq} "
                f"into {self.path}; {lost}")


class NothingToRecover(RecordingError):
    """The recording is finished: there is nothing to recover (not a failure of ``recover``)."""


def default_output(source: Path) -> Path:
    return source.with_name(source.stem + ".recovered.mcap")


def recover(source, out=None, *, overwrite: bool = False) -> Recovered:
    """Write the complete chunks of the truncated recording ``source`` as a finished
    file (default ``<name>.recovered.mcap`` beside it).  Raises RecordingError naming
    the file when there is nothing to recover (NothingToRecover: the file is finished; or unreadable)
    or the output exists (unless ``overwrite``)."""
    source = Path(source)
    episode = read_episode(source, salvage=True)
    if episode.complete:
        raise NothingToRecover(f"{source}: a finished recording (footer and summary read through): nothing to recover")
    path = Path(out) if out is not None else default_output(source)
    if path.resolve() == source.resolve():
        raise RecordingError(f"{path}: the output must not be the truncated file itself (it is kept as it is)")
    if path.is_dir():
        raise RecordingError(f"{path}: a folder; the output is a file (e.g. {path / default_output(source).name})")
    if not path.parent.is_dir():
        raise RecordingError(f"{path}: its folder {path.parent} does not exist")
    if path.exists() and not overwrite:
        raise RecordingError(f"{path}: exists (pass --force to replace it)")

    write_copy(episode, path, library=f"{episode.library}; recovered by etar-bench recover",
               metadata=dict(episode.metadata, recovered=episode.problem or "", recovered_from=source.name),
               what="recovered")
    last_seq = None
    for m in episode.messages:
        if m.topic == ROBOT_STATE.channel:
            try:
                msg = loads(m.payload)
            except ValueError:
                continue  # recorded as received, garbage included
            seq = msg.get("seq") if isinstance(msg, dict) else None
            if type(seq) is int and (last_seq is None or seq > last_seq):  # not a bool
                last_seq = seq
    return Recovered(source, path, len(episode.messages), episode.chunks, last_seq, episode.problem or "")


def write_copy(episode, path: Path, *, library: str, metadata: dict, extra=(), what: str = "new") -> None:
    """Write ``episode`` (``read_episode``) as a finished MCAP file at ``path``: its
    channels, schemas, scenario and messages byte for byte, ``metadata`` as its
    metadata record, and ``extra`` messages on channels of their own (``(topic,
    schema_name, schema_data, log_time_ns, payload)``, JSON with a JSON Schema) in log
    time order with the rest.  Written beside as ``.part``, read back and compared
    (the episode's messages must all be there, unchanged), then moved into place:
    a failure leaves ``path`` as it was."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    try:
        with open(tmp, "wb") as f:
            # as services.recordings.writer writes them: no index for a group that is empty
            index_types = IndexType.CHUNK | IndexType.MESSAGE | IndexType.METADATA
            if episode.attachments:
                index_types |= IndexType.ATTACHMENT
            writer = Writer(f, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD, index_types=index_types)
            writer.start(profile="", library=library)
            writer.add_metadata(METADATA_NAME, metadata)
            for name, data in episode.attachments.items():
                writer.add_attachment(create_time=0, log_time=0, name=name, media_type=_media_type(name), data=data)
            schema_ids: dict[tuple, int] = {}
            channel_ids: dict[str, int] = {}
            channels = [(topic, ch.schema_name, ch.schema_encoding, ch.schema_data, ch.message_encoding, ch.metadata)
                        for topic, ch in sorted(episode.channels.items())]
            for topic, name, data in dict.fromkeys((t, n, d) for t, n, d, _, _ in extra):
                channels.append((topic, name, "jsonschema", data, "json", {"derived_by": DERIVED_BY}))
            for topic, name, encoding, data, message_encoding, meta in channels:
                key = (name, encoding, data)
                if name and key not in schema_ids:
                    schema_ids[key] = writer.register_schema(name=name, encoding=encoding, data=data)
                channel_ids[topic] = writer.register_channel(topic=topic, message_encoding=message_encoding,
                                                             schema_id=schema_ids.get(key, 0), metadata=meta)
            rows = [(m.log_time_ns, 0, i, m.topic, m.payload, m.publish_time_ns) for i, m in enumerate(episode.messages)]
            rows += [(t, 1, i, topic, payload, t) for i, (topic, _, _, t, payload) in enumerate(extra)]
            for log_time, _, _, topic, payload, publish_time in sorted(rows, key=lambda r: r[:3]):
                writer.add_message(channel_id=channel_ids[topic], log_time=log_time, data=payload,
                                   publish_time=publish_time)
            writer.finish()

        back = read_episode(tmp)
        kept = [tuple(m) for m in back.messages if m.topic in episode.channels]
        if not back.complete or kept != [tuple(m) for m in episode.messages] or \
                len(back.messages) != len(episode.messages) + len(extra):
            tmp.unlink()
            raise RecordingError(f"{path}: the {what} file did not read back as written; nothing was written")
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a failed write (a full disk, Ctrl-C) leaves nothing behind
        raise


def _media_type(name: str) -> str:
    return SCENARIO_MEDIA_TYPE if name == SCENARIO_ATTACHMENT else "application/octet-stream"
