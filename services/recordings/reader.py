"""Reading a recording back.

``read_episode`` walks the file forward with mcap's ``StreamReader``, not with
``make_reader``: the seeking reader starts from the footer at the end of the file,
so it cannot open a file whose writer never finished, whereas the stream reader
hands out the records of a chunk only once the whole chunk has been read and its
CRC checked.  What a truncated file (a recorder killed mid-run) recovers is
therefore: the metadata, the scenario attachment, and every message of every
chunk that was completely written; the messages of the chunk being written when
the process died (at most ``CHUNK_SIZE`` of JSON, about 100 robot cycles) are
lost.  Such an episode has ``complete = False`` and ``problem`` says what was
lost; a file cut before its metadata record says nothing worth keeping and
raises.  A file read through its footer whose closing magic is cut or damaged (a
copy a few bytes short) lost nothing: ``complete = False``, every message read.  A
file that is not MCAP, or a finished file (with its closing magic) that does not
read through, raises ``RecordingError`` naming the file.
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import zstandard
from mcap.exceptions import McapError, RecordLengthLimitExceeded
from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema, Statistics
from mcap.stream_reader import StreamReader, breakup_chunk

from services.recordings.format import MAGIC, METADATA_NAME, SCENARIO_ATTACHMENT, WALL_CLOCK_TOPICS, RecordingError
from services.runtime.messages import ROBOT_STATE, SEQ_PREFIX, loads
from services.runtime.visual_topics import SCHEMA_NAMES as VISUAL_SCHEMA_NAMES


class RecordedMessage(NamedTuple):
    topic: str  # without the run prefix, e.g. "/robot/state"
    log_time_ns: int
    payload: bytes  # exactly as received
    publish_time_ns: int = 0


@dataclass(frozen=True)
class ChannelInfo:
    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    metadata: dict


@dataclass
class Episode:
    path: Path
    messages: list[RecordedMessage]  # in log-time order (file order among equal times)
    metadata: dict[str, str]  # the "etar" metadata record ({} if absent)
    attachments: dict[str, bytes]
    channels: dict[str, ChannelInfo]  # topic -> channel and schema
    complete: bool  # the file was finished (footer, summary) and reads through
    problem: str | None = None  # why it is incomplete
    library: str = ""
    chunks: int = 0  # chunks read whole

    @property
    def scenario_text(self) -> str | None:
        data = self.attachments.get(SCENARIO_ATTACHMENT)
        return None if data is None else data.decode("utf-8", errors="replace")

    def topics(self) -> list[str]:
        return sorted({m.topic for m in self.messages})


# what a damaged file can make the mcap library raise: its own errors, short
# reads inside struct/str decoding, CRC and UTF-8 errors (ValueError), zstd's
# and lz4's (RuntimeError) decompression errors, and a bogus size field
# OverflowError: a damaged length field (e.g. 2^63) that the mcap reader passes on to read()
_READ_ERRORS = (McapError, struct.error, ValueError, EOFError, zstandard.ZstdError, RuntimeError, MemoryError,
                OverflowError)


def compared_messages(path) -> tuple[list[tuple[str, int, str]], bool]:
    """What the seed determines of one recording, in the file's order: every message but
    the wall-clock and the visual ones, as (topic, seq, payload without ``sent_ns`` as JSON
    with sorted keys); a payload that is not a message is kept as its bytes' repr with
    seq -1.  And whether the file is complete.  The one rule by which two runs' recordings
    are compared (``recorded_content``, ``etar-bench diff``)."""
    ep = read_episode(path)
    out = []
    for m in ep.messages:
        if m.topic in WALL_CLOCK_TOPICS or m.topic in VISUAL_SCHEMA_NAMES:
            continue
        try:
            d = loads(m.payload)
            seq = d["seq"]
            # a foreign peer's JSON with a seq of another kind is no message either: keys
            # of mixed kinds would not sort
            if type(seq) is not int:
                raise TypeError(f"seq is {type(seq).__name__}")
            d.pop("sent_ns", None)
            text = json.dumps(d, sort_keys=True)
        except (ValueError, TypeError, KeyError, AttributeError):  # not a message: compared as bytes
            seq, text = -1, repr(m.payload)
        out.append((m.topic, seq, text))
    return out, ep.complete


def recorded_content(run_dir) -> dict:
    """Per recording file of a run directory, what the seed determines (``compared_messages``),
    sorted.  Two runs of one seed compare equal, over Zenoh or in one process.  The visual
    topics are left out: the recorder derives them from the newest messages it has when a
    state arrives, which over a network depends on the order of arrival."""
    return {path.name: sorted(compared_messages(path)[0])
            for path in sorted((Path(run_dir) / "recordings").glob("*.mcap"))}


def recording_kind(path) -> str | None:
    """The ``episode_kind`` of a recording's metadata record ('demonstration',
    'reproduction'), read from the start of the file, where the writer puts it; None
    when the file does not say (``read_episode`` then names what is wrong)."""
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            for record in StreamReader(f, emit_chunks=True, record_size_limit=size).records:
                if isinstance(record, Metadata) and record.name == METADATA_NAME:
                    return record.metadata.get("episode_kind")
                if isinstance(record, (Chunk, Message, DataEnd, Footer)):
                    return None  # past where the writer puts it
    except (OSError, *_READ_ERRORS):
        return None
    return None


def read_episode(path, *, salvage: bool = False) -> Episode:
    """Read one recording; see the module docstring for truncated files.  ``salvage``: a
    finished file damaged inside (a chunk that fails its CRC or does not decompress) gives
    what was read before the damage, incomplete, instead of a RecordingError (``recover``)."""
    path = Path(path)
    if path.exists() and not path.is_file():  # a FIFO would block the open, /dev/zero never end
        raise RecordingError(f"{path}: not a regular file" + (" (a folder)" if path.is_dir() else ""))
    try:
        f = open(path, "rb")
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such file") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot open ({exc})") from None
    with f:
        size = os.fstat(f.fileno()).st_size
        if size < 2 * len(MAGIC):
            raise RecordingError(f"{path}: not an MCAP file ({size} bytes)")
        f.seek(-len(MAGIC), os.SEEK_END)
        ends_with_magic = f.read() == MAGIC
        f.seek(0)
        scan = _Scan()
        error = None
        # a record longer than the file is damage: refuse it rather than allocate it
        reader = StreamReader(f, validate_crcs=True, emit_chunks=True, record_size_limit=size)
        try:
            for record in reader.records:  # ends after the footer and the closing magic
                scan.take(record)
        except _READ_ERRORS as exc:
            error = exc

    if scan.header is None:
        raise RecordingError(f"{path}: not a readable MCAP file ({_describe(error)})") from error
    problem = None
    # read through the footer, only the closing magic cut (a copy a few bytes short) or damaged:
    # every record before it was read
    magic_cut = error is not None and scan.footer is not None and not ends_with_magic
    if magic_cut:
        problem = (f"the closing magic bytes are cut or damaged ({_describe(error)}); every record before them "
                   "was read")
    elif error is not None:
        damaged = scan.footer is not None or ends_with_magic  # the writer finished it: damaged, not cut short
        if damaged and not (salvage and scan.metadata and (scan.chunks or scan.data_end)):
            raise RecordingError(f"{path}: corrupt MCAP file ({_describe(error)}); {scan.chunks} chunk(s), "
                                 f"{len(scan.rows)} message(s) read before the damage") from error
        if not scan.metadata:
            # not even which run and episode it was: nothing worth returning
            raise RecordingError(f"{path}: truncated MCAP file, cut before its {METADATA_NAME!r} metadata record "
                                 f"({_describe(error)})") from error
        recovered = ("the data section is complete: every message was recovered, only the summary is lost"
                     if scan.data_end else f"{scan.chunks} complete chunk(s) recovered; the messages of the "
                     "chunk " + ("found damaged and after it" if damaged else "being written when the file ended") +
                     " are lost")
        problem = (f"corrupt MCAP file ({_describe(error)}); {recovered}" if damaged else
                   f"no MCAP footer: the writer did not finish (killed, or the file copied while recording); "
                   f"{_describe(error)}; {recovered}")
    if (error is None or magic_cut) and scan.statistics is not None and \
            scan.statistics.message_count != len(scan.rows):
        raise RecordingError(f"{path}: corrupt MCAP file (the summary counts {scan.statistics.message_count} "
                             f"messages, the chunks hold {len(scan.rows)})")

    # sort is stable: messages with equal log times keep their file order
    scan.rows.sort(key=lambda r: r.log_time_ns)
    infos = {}
    for ch in scan.channels.values():
        s = scan.schemas.get(ch.schema_id)
        infos[ch.topic] = ChannelInfo(ch.topic, ch.message_encoding, s.name if s else "", s.encoding if s else "",
                                      s.data if s else b"", dict(ch.metadata))
    return Episode(path=path, messages=scan.rows, metadata=scan.metadata, attachments=scan.attachments,
                   channels=infos, complete=error is None, problem=problem, library=scan.header.library,
                   chunks=scan.chunks)


class _Scan:
    """The records of one forward pass through a file."""

    def __init__(self):
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.rows: list[RecordedMessage] = []
        self.metadata: dict[str, str] = {}
        self.attachments: dict[str, bytes] = {}
        self.header = self.footer = self.statistics = None
        self.data_end = False
        self.chunks = 0  # read whole, CRC checked

    def take(self, record) -> None:
        if isinstance(record, Chunk):
            # all of a chunk or nothing of it
            mark = len(self.rows)
            try:
                for inner in breakup_chunk(record, validate_crc=True):
                    if isinstance(inner, Message):  # nearly every record of a chunk: asked first
                        self._message(inner)
                    else:
                        self.take(inner)
            except _READ_ERRORS:
                del self.rows[mark:]
                raise
            self.chunks += 1
        elif isinstance(record, Message):
            self._message(record)
        elif isinstance(record, Channel):
            if record.schema_id != 0 and record.schema_id not in self.schemas:
                raise McapError(f"channel {record.topic!r} refers to unknown schema {record.schema_id}")
            self.channels[record.id] = record
        elif isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Header):
            self.header = record
        elif isinstance(record, Metadata):
            if record.name == METADATA_NAME:
                self.metadata.update(record.metadata)
        elif isinstance(record, Attachment):
            self.attachments[record.name] = record.data
        elif isinstance(record, DataEnd):
            self.data_end = True
        elif isinstance(record, Statistics):
            self.statistics = record
        elif isinstance(record, Footer):
            self.footer = record

    def _message(self, record) -> None:
        ch = self.channels.get(record.channel_id)
        if ch is None:
            raise McapError(f"message on unknown channel {record.channel_id}")
        self.rows.append(RecordedMessage(ch.topic, record.log_time, record.data, record.publish_time))


def _describe(exc: BaseException | None) -> str:
    if exc is None:
        return "no records"
    text = str(exc)
    if isinstance(exc, RecordLengthLimitExceeded):
        # the limit is the file size, so the record runs past the end of the file
        text += " (the file size): the file ends inside it"
    return f"{type(exc).__name__}: {text}" if text else f"{type(exc).__name__} (unexpected end of file)"



def recording_gaps(paths) -> list:
    """The robot cycles that none of an episode's recording parts holds (a recorder
    restarted mid-episode wrote on in a further part): per pair of consecutive parts,
    the last robot_state cycle of the one and the first of the next, and how many
    cycles lie between; with each part's problem if it was cut short."""
    ranges = []
    for path in paths:
        try:
            ep = read_episode(path)
        except RecordingError as exc:
            ranges.append((str(path), None, None, str(exc)))
            continue
        seqs = [int(m.group(1)) for msg in ep.messages if msg.topic == ROBOT_STATE.channel
                for m in [SEQ_PREFIX.match(msg.payload)] if m]
        ranges.append((str(path), min(seqs, default=None), max(seqs, default=None), ep.problem or ""))
    gaps = []
    for (path, _, last, problem), (nxt, first, _, _) in zip(ranges, ranges[1:]):
        missing = first - last - 1 if last is not None and first is not None else None
        gaps.append({"part": path, "last_cycle": last, "next_part": nxt, "next_first_cycle": first,
                     "cycles_missing": missing, "part_problem": problem})
    return gaps
