"""Recordings: one MCAP file per episode (a demonstration or a reproduction).

Writing (``EpisodeWriter``) is a narrow format object over ``mcap.writer.Writer``:
the recorder hands it, per received sample, the key expression, the payload
bytes and the receive time, and the payload goes into the file unchanged, so a
recording is exactly what crossed the wire.  Each topic becomes a channel with
``message_encoding="json"`` and a ``jsonschema`` schema taken from
``services.runtime.messages`` (Foxglove opens the files as they are).

Times are integer nanoseconds.  ``log_time`` is the recorder's receive time on
CLOCK_MONOTONIC; ``publish_time`` is the message's ``sent_ns`` header (the same
clock, on one host), or the receive time when the payload does not decode.  The
``etar`` metadata record states this epoch.

Layout, chosen so a killed recorder loses little: the header, the ``etar``
metadata record and the ``scenario.yaml`` attachment come first; messages
follow in zstd chunks of about 256 KiB; the summary (statistics, chunk and
message indexes) is written by ``finish()``.  Indexes are written only for
groups that cannot be empty (chunks, messages, metadata, and attachments when
there is a scenario): mcap's default writer emits summary offsets for empty
groups, which MCAP validators flag.

Reading (``read_episode``) walks the file forward with mcap's ``StreamReader``,
not with ``make_reader``: the seeking reader starts from the footer at the end
of the file, so it cannot open a file whose writer never finished, whereas the
stream reader hands out the records of a chunk only once the whole chunk has
been read and its CRC checked.  What a truncated file (a recorder killed
mid-run) recovers is therefore: the metadata, the scenario attachment, and
every message of every chunk that was completely written; the messages of the
chunk being written when the process died (at most ``CHUNK_SIZE`` of JSON,
about 100 robot cycles) are lost.  Such an episode has ``complete = False`` and
``problem`` says what was lost; a file cut before its metadata record says
nothing worth keeping and raises.  A file that is not MCAP, or a finished
file (with its closing magic) that does not read through, raises
``RecordingError`` naming the file.

``load_demonstration`` turns one recorded demonstration into the arrays the
ETAR learner takes; ``services.etar_cli`` registers it for ``.mcap`` files.
"""

from __future__ import annotations

import json
import math
import numbers
import os
import pickle
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import zstandard
from mcap.exceptions import McapError, RecordLengthLimitExceeded
from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema, Statistics
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, IndexType, Writer

from services.features import force_vector, state_vector
from services.runtime.messages import (BY_TOPIC, FT_WRENCH, ROBOT_CONTACT, ROBOT_STATE, SEQ_PREFIX, MessageError,
                                      MessageType)
from services.visual import SCHEMA_NAMES as VISUAL_SCHEMA_NAMES, schema_bytes as visual_schema

# bytes of uncompressed records per chunk: what a killed recorder can lose.  A
# reproduction records 1.94 MB per simulated second, a demonstration 1.60 MB
# (smoke scenario over Zenoh), so a chunk holds 84 ms or 102 ms of the episode
CHUNK_SIZE = 160 * 1024
METADATA_NAME = "etar"
SCENARIO_ATTACHMENT = "scenario.yaml"
SCENARIO_MEDIA_TYPE = "application/yaml"
MAGIC = b"\x89MCAP0\r\n"

_GENERIC_SCHEMA_NAME = "json_object"
_UINT64 = 2**64


class RecordingError(ValueError):
    """A recording that cannot be written or read, naming the file and what is wrong."""


# ---------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------


class EpisodeWriter:
    """One MCAP file for one episode.  ``add`` every sample, then ``finish``
    (or use it as a context manager).  Thread-safe: Zenoh may call the
    recorder's callback from more than one thread, and mcap's Writer is not."""

    def __init__(self, path, *, run_id: str, episode_kind: str, episode_index: int,
                 scenario_text: str | None = None, metadata: dict | None = None):
        if not run_id or "/" in run_id or any(c in run_id for c in "*$?#"):
            raise RecordingError(f"run_id must be one key-expression chunk, got {run_id!r}")
        self.path = Path(path)
        self.run_id = run_id
        self.prefix = f"etar/{run_id}/"
        self.messages_written = 0
        self.bad_payloads = 0
        self._lock = threading.Lock()
        self._schemas: dict[str, int] = {}  # schema name -> id
        self._channels: dict[str, tuple[int, MessageType | None]] = {}  # key expression -> (id, type)
        self._finished = False

        record = {"run_id": run_id, "episode_kind": str(episode_kind), "episode_index": str(int(episode_index)),
                  "log_time": "CLOCK_MONOTONIC ns at reception (recorder)",
                  "publish_time": "sent_ns header, CLOCK_MONOTONIC ns (log time if the payload does not decode)"}
        for k, v in (metadata or {}).items():
            if str(k) in record:
                raise RecordingError(f"{self.path}: metadata key {k!r} is reserved for the recorder")
            record[str(k)] = str(v)

        # indexes only for groups that cannot be empty (module docstring); the
        # attachment and metadata indexes let seeking readers (Foxglove) list them
        index_types = IndexType.CHUNK | IndexType.MESSAGE | IndexType.METADATA
        if scenario_text is not None:
            index_types |= IndexType.ATTACHMENT
        try:
            self._file = open(self.path, "wb")
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot create the recording ({exc})") from None
        try:
            self._writer = Writer(self._file, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD,
                                  index_types=index_types)
            self._writer.start(profile="", library=f"etar-testbench services.recording; {LIBRARY_IDENTIFIER}")
            self._writer.add_metadata(METADATA_NAME, record)
            if scenario_text is not None:
                now = time.monotonic_ns()
                self._writer.add_attachment(create_time=now, log_time=now, name=SCENARIO_ATTACHMENT,
                                            media_type=SCENARIO_MEDIA_TYPE, data=scenario_text.encode("utf-8"))
            # on disk now, so that a recorder killed before its first chunk still
            # leaves a file that says which episode it was
            self._file.flush()
        except BaseException:
            self._file.close()
            raise

    # ------------------------------------------------------------------ data

    def add(self, key_expr: str, payload: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Record one sample as received.  A payload that does not decode is
        recorded all the same (and counted in ``bad_payloads``): the recording
        is the evidence of what was sent.  Passing ``publish_time_ns`` skips
        decoding (and so the bad-payload check).  A key expression outside
        ``etar/<run_id>/`` raises ``RecordingError`` and is not recorded."""
        if not isinstance(payload, (bytes, bytearray, memoryview)):
            raise TypeError(f"payload must be bytes, got {type(payload).__name__}")
        log_time_ns = _check_time("log_time_ns", log_time_ns)
        if publish_time_ns is not None:
            publish_time_ns = _check_time("publish_time_ns", publish_time_ns)
        data = bytes(payload)
        with self._lock:
            if self._finished:
                raise RecordingError(f"{self.path}: add() after finish()")
            entry = self._channels.get(key_expr)
            if entry is None:
                entry = self._register(key_expr)
            channel_id, mtype = entry
            if publish_time_ns is None:
                sent = self._sent_ns(mtype, data)
                publish_time_ns = log_time_ns if sent is None else sent
            self._writer.add_message(channel_id=channel_id, log_time=log_time_ns, data=data,
                                     publish_time=publish_time_ns)
            self.messages_written += 1

    def _sent_ns(self, mtype: MessageType | None, data: bytes) -> int | None:
        try:
            if mtype is not None:
                msg = mtype.decode(data)
            else:
                msg = json.loads(data)
                if not isinstance(msg, dict):
                    raise MessageError("not a JSON object")
        except (MessageError, ValueError, UnicodeDecodeError):
            self.bad_payloads += 1
            return None
        sent = msg.get("sent_ns")
        if isinstance(sent, int) and not isinstance(sent, bool) and 0 <= sent < _UINT64:
            return sent
        return None

    def _register(self, key_expr: str) -> tuple[int, MessageType | None]:
        if key_expr in VISUAL_SCHEMA_NAMES:
            return self._register_visual(key_expr)
        if not key_expr.startswith(self.prefix) or len(key_expr) == len(self.prefix):
            raise RecordingError(f"{self.path}: key expression {key_expr!r} is not under {self.prefix!r}")
        suffix = key_expr[len(self.prefix):]
        mtype = BY_TOPIC.get(suffix)
        name = mtype.name if mtype is not None else _GENERIC_SCHEMA_NAME
        schema_id = self._schemas.get(name)
        if schema_id is None:
            schema = mtype.json_schema() if mtype is not None else _generic_schema()
            schema_id = self._writer.register_schema(name=name, encoding="jsonschema",
                                                     data=json.dumps(schema, separators=(",", ":")).encode())
            self._schemas[name] = schema_id
        channel_id = self._writer.register_channel(topic="/" + suffix, message_encoding="json",
                                                   schema_id=schema_id, metadata={"key_expr": key_expr})
        self._channels[key_expr] = (channel_id, mtype)
        return channel_id, mtype

    def _register_visual(self, topic: str) -> tuple[int, None]:
        """A visual topic (services.visual): derived by the recorder, not received, so under
        its own name (/viz/...) with Foxglove's schema, beside the run's topics."""
        name = VISUAL_SCHEMA_NAMES[topic]
        schema_id = self._schemas.get(name)
        if schema_id is None:
            schema_id = self._writer.register_schema(name=name, encoding="jsonschema", data=visual_schema(topic))
            self._schemas[name] = schema_id
        channel_id = self._writer.register_channel(topic=topic, message_encoding="json", schema_id=schema_id,
                                                   metadata={"derived_by": "services.visual"})
        self._channels[topic] = (channel_id, None)
        return channel_id, None

    # -------------------------------------------------------------- lifetime

    def finish(self) -> None:
        """Write the last chunk and the summary, and close the file.  Idempotent."""
        with self._lock:
            if self._finished:
                return
            self._finished = True
            try:
                self._writer.finish()
            finally:
                self._file.close()

    @property
    def finished(self) -> bool:
        return self._finished

    def __enter__(self) -> EpisodeWriter:
        return self

    def __exit__(self, *exc) -> None:
        # finish even on error: whatever was recorded stays readable
        self.finish()


class WriterProcess:
    """``EpisodeWriter`` s run in a helper process, fed over a pipe in batches.

    What an in-process run does instead of writing MCAP on its own thread: every
    node of the run shares one CPU and its GIL, and turning each message into MCAP
    records (the mcap library's Python) took a fifth of each simulated millisecond.
    The helper writes the same files with the same writer.  ``open`` and ``finish``
    wait for the helper (an error names the file); ``add`` only queues.  If this
    process dies, the helper finishes the open file with what it was sent."""

    BATCH = 2000  # messages per hand-over

    def __init__(self):
        import subprocess
        import sys

        # its own interpreter (not multiprocessing: that re-imports the caller's main
        # script, and forking copies the run's threads)
        self._proc = subprocess.Popen([sys.executable, "-m", "services.recording", "--writer-process"],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=None)

    def _call(self, *request):
        try:
            self._send(request)
            ok, value = pickle.load(self._proc.stdout)
        except (EOFError, OSError, pickle.UnpicklingError) as exc:
            raise RecordingError(f"the MCAP writer process is gone ({type(exc).__name__}: {exc}; exit code "
                                 f"{self._proc.poll()})") from None
        if not ok:
            raise RecordingError(value)
        return value

    def _send(self, request) -> None:
        pickle.dump(request, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        self._proc.stdin.flush()

    def open(self, path, **kwargs) -> "OffloadedEpisodeWriter":
        self._call("open", str(path), kwargs)
        return OffloadedEpisodeWriter(self, Path(path))

    def send(self, batch: list) -> None:
        try:
            self._send(("add", batch))
        except OSError as exc:
            raise RecordingError(f"the MCAP writer process is gone ({exc}; exit code {self._proc.poll()})") from None

    def close(self) -> None:
        try:
            self._send(("close",))
            self._proc.stdin.close()
        except OSError:
            pass
        try:
            self._proc.wait(10)
        except Exception:
            self._proc.kill()
            self._proc.wait()
        self._proc.stdout.close()


class OffloadedEpisodeWriter:
    """The parent's side of one file a ``WriterProcess`` writes (``EpisodeWriter``'s interface)."""

    def __init__(self, process: WriterProcess, path: Path):
        self._process = process
        self.path = path
        self._batch: list = []
        self.messages_written = 0
        self.bad_payloads = 0
        self._finished = False

    def add(self, key_expr: str, payload: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        if self._finished:
            raise RecordingError(f"{self.path}: add() after finish()")
        self._batch.append((key_expr, bytes(payload), log_time_ns, publish_time_ns))
        if len(self._batch) >= WriterProcess.BATCH:
            self._process.send(self._batch)
            self._batch = []

    def finish(self) -> None:
        if self._finished:
            return
        self._finished = True
        if self._batch:
            self._process.send(self._batch)
            self._batch = []
        self.messages_written, self.bad_payloads = self._process._call("finish")

    @property
    def finished(self) -> bool:
        return self._finished


def _writer_main(requests, replies) -> None:
    """The helper process: open / add / finish / close requests, until the pipe closes."""
    writer = None

    def reply(value) -> None:
        pickle.dump(value, replies, protocol=pickle.HIGHEST_PROTOCOL)
        replies.flush()

    try:
        while True:
            try:
                request = pickle.load(requests)
            except EOFError:
                return  # the parent is gone: the finally below finishes the open file
            kind = request[0]
            if kind == "add":
                if writer is not None:
                    for key, raw, log, pub in request[1]:
                        writer.add(key, raw, log, pub)
                continue
            if kind == "close":
                return
            try:
                if kind == "open":
                    if writer is not None:
                        writer.finish()
                    writer = EpisodeWriter(request[1], **request[2])
                    reply((True, None))
                elif kind == "finish":
                    w, writer = writer, None
                    if w is None:
                        raise RecordingError("no episode is being recorded")
                    w.finish()
                    reply((True, (w.messages_written, w.bad_payloads)))
            except Exception as exc:  # the parent raises it, naming the file
                reply((False, f"{type(exc).__name__}: {exc}"))
    finally:
        if writer is not None:
            writer.finish()


def _check_time(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer number of nanoseconds, got {value!r}")
    value = int(value)
    if not 0 <= value < _UINT64:
        raise RecordingError(f"{name} must be within [0, 2**64) ns, got {value}")
    return value


def _generic_schema() -> dict:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": _GENERIC_SCHEMA_NAME,
            "description": "a topic without a message definition in services.runtime.messages: any JSON object",
            "type": "object"}


# ---------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------


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


# topics whose payloads carry wall-clock durations and loop timing, and the services' log lines
# (when a service logs is the machine's doing): not what a seed determines
WALL_CLOCK_TOPICS = frozenset({"/robot/episode", "/runner/event", "/service/log"})


def recorded_content(run_dir) -> dict:
    """Per recording file of a run directory, what the seed determines: every message
    but the wall-clock ones, as (topic, seq, payload without ``sent_ns``), sorted.  Two
    runs of one seed compare equal, over Zenoh or in one process.  The visual topics
    are left out: the recorder derives them from the newest messages it has when a
    state arrives, which over a network depends on the order of arrival."""
    out = {}
    for path in sorted((Path(run_dir) / "recordings").glob("*.mcap")):
        msgs = []
        for m in read_episode(path).messages:
            if m.topic in WALL_CLOCK_TOPICS or m.topic in VISUAL_SCHEMA_NAMES:
                continue
            d = json.loads(m.payload)
            d.pop("sent_ns", None)
            msgs.append((m.topic, d["seq"], json.dumps(d, sort_keys=True)))
        out[path.name] = sorted(msgs)
    return out


def read_episode(path) -> Episode:
    """Read one recording; see the module docstring for truncated files."""
    path = Path(path)
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
    if error is not None:
        if scan.footer is not None or ends_with_magic:
            # the writer finished this file, so it is damaged, not cut short
            raise RecordingError(f"{path}: corrupt MCAP file ({_describe(error)}); {scan.chunks} chunk(s), "
                                 f"{len(scan.rows)} message(s) read before the damage") from error
        if not scan.metadata:
            # not even which run and episode it was: nothing worth returning
            raise RecordingError(f"{path}: truncated MCAP file, cut before its {METADATA_NAME!r} metadata record "
                                 f"({_describe(error)})") from error
        recovered = ("the data section is complete: every message was recovered, only the summary is lost"
                     if scan.data_end else f"{scan.chunks} complete chunk(s) recovered; the messages of the "
                     "chunk being written when the file ended are lost")
        problem = (f"no MCAP footer: the writer did not finish (killed, or the file copied while recording); "
                   f"{_describe(error)}; {recovered}")
    elif scan.statistics is not None and scan.statistics.message_count != len(scan.rows):
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
                    self.take(inner)
            except _READ_ERRORS:
                del self.rows[mark:]
                raise
            self.chunks += 1
        elif isinstance(record, Message):
            ch = self.channels.get(record.channel_id)
            if ch is None:
                raise McapError(f"message on unknown channel {record.channel_id}")
            self.rows.append(RecordedMessage(ch.topic, record.log_time, record.data, record.publish_time))
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


def _describe(exc: BaseException | None) -> str:
    if exc is None:
        return "no records"
    text = str(exc)
    if isinstance(exc, RecordLengthLimitExceeded):
        # the limit is the file size, so the record runs past the end of the file
        text += " (the file size): the file ends inside it"
    return f"{type(exc).__name__}: {text}" if text else f"{type(exc).__name__} (unexpected end of file)"


# ---------------------------------------------------------------------------
# demonstrations for the learner
# ---------------------------------------------------------------------------

STATE_KINDS = {"position": 3, "pose": 6}
FEATURE_KINDS = {"force": 3, "force_torque": 6}
_DEMONSTRATION_TOPICS = {"/robot/state": ROBOT_STATE, "/ft/wrench": FT_WRENCH, "/robot/contact": ROBOT_CONTACT}


def load_demonstration(path, *, state: str = "position", features: str = "force", rate_hz: float = 100.0,
                       allow_incomplete: bool = False) -> dict:
    """One recorded demonstration as the ETAR learner takes it.

    Robot cycles (``seq``) that have a robot_state, an ft_wrench and a
    robot_contact are kept, then subsampled to the cycles whose robot_state
    ``stamp_ns`` (simulation time) is a whole multiple of the sample period:
    deterministic, and the same instants whatever cycle the recording began on.

    Returns ``states`` (T, 3) tcp position [m] or (T, 6) position + rotation
    vector of R_0^T R (relative to the first sample; ``services.features``); ``forces``
    (T, 3) the F/T force, or (T, 6) force and torque, in base axes (the sensor
    has the tcp's orientation, so f_base = R f_sensor); ``phases`` (T-1,) the
    true phase of samples 1..T-1 (the label of step t -> t+1 is the phase at
    t+1); ``dt`` [s]; ``t`` (T,) [s] simulation time; ``seq`` (T,) robot
    cycles; ``skipped`` messages that did not decode or repeated a cycle;
    ``gaps`` sample instants between the first and the last with no complete
    cycle; ``complete`` and ``problem`` (``read_episode``'s); ``path``.  An
    incomplete recording raises unless ``allow_incomplete``.
    """
    path = Path(path)
    if state not in STATE_KINDS:
        raise RecordingError(f"state must be one of {sorted(STATE_KINDS)}, got {state!r}")
    if features not in FEATURE_KINDS:
        raise RecordingError(f"features must be one of {sorted(FEATURE_KINDS)}, got {features!r}")
    period_ns = _sample_period_ns(rate_hz)
    episode = read_episode(path)
    if not episode.complete and not allow_incomplete:
        raise RecordingError(f"{path}: incomplete recording: {episode.problem}; {len(episode.messages)} "
                             "message(s) recovered (load_demonstration(..., allow_incomplete=True) uses them)")

    by_seq: dict[str, dict[int, dict]] = {topic: {} for topic in _DEMONSTRATION_TOPICS}
    skipped = 0
    for msg in episode.messages:
        mtype = _DEMONSTRATION_TOPICS.get(msg.topic)
        if mtype is None:
            continue
        try:
            decoded = mtype.decode(msg.payload)
        except MessageError:
            skipped += 1
            continue
        table = by_seq[msg.topic]
        if decoded["seq"] in table:
            skipped += 1  # a repeated cycle: the first one is what the robot sent
            continue
        table[decoded["seq"]] = decoded
    for topic, table in by_seq.items():
        if not table:
            found = ", ".join(episode.topics()) or "none"
            raise RecordingError(f"{path}: no {topic} messages that decode "
                                 f"({skipped} skipped; topics in the file: {found})")
    states_by_seq, ft_by_seq, contact_by_seq = (by_seq[t] for t in _DEMONSTRATION_TOPICS)
    # cycles of no episode (episode -1: the arm resting while the sensor is tared) are not demonstration
    states_by_seq = {k: v for k, v in states_by_seq.items() if v.get("episode", 0) != -1} or states_by_seq
    cycles = sorted(states_by_seq.keys() & ft_by_seq.keys() & contact_by_seq.keys())
    if not cycles:
        ranges = "; ".join(f"{t} seq {min(v)}..{max(v)}" for t, v in by_seq.items())
        raise RecordingError(f"{path}: no robot cycle has all of /robot/state, /ft/wrench and /robot/contact "
                             f"({ranges})")
    # the robot cycle, from consecutive cycles: a sample period that is not a
    # multiple of it would pick instants at uneven intervals
    steps = [states_by_seq[b]["stamp_ns"] - states_by_seq[a]["stamp_ns"]
             for a, b in zip(cycles, cycles[1:]) if b == a + 1]
    cycle_ns = int(np.median(steps)) if steps else 0
    if cycle_ns <= 0 or period_ns % cycle_ns:
        raise RecordingError(f"{path}: the sample period {period_ns} ns ({rate_hz} Hz) must be a multiple of the "
                             f"robot cycle ({cycle_ns} ns, from {len(steps)} consecutive cycles)")
    chosen = [s for s in cycles if states_by_seq[s]["stamp_ns"] % period_ns == 0]
    if len(chosen) < 2:
        raise RecordingError(f"{path}: {len(chosen)} sample(s) at {rate_hz} Hz from {len(cycles)} complete "
                             "robot cycles; a demonstration needs at least 2")

    stamp_ns = np.array([states_by_seq[s]["stamp_ns"] for s in chosen], dtype=np.int64)
    if np.any(np.diff(stamp_ns) <= 0):
        raise RecordingError(f"{path}: robot_state stamp_ns does not increase with seq")
    cart = np.array([states_by_seq[s]["msr_cart_pos"] for s in chosen], dtype=np.float64).reshape(-1, 3, 4)
    R = cart[:, :, :3]
    wrench = np.array([ft_by_seq[s]["wrench"] for s in chosen], dtype=np.float64)
    true_phase = np.array([contact_by_seq[s]["true_phase"] for s in chosen], dtype=np.int64)

    # the same functions as the online estimator, so learner and estimator see the same numbers
    R0 = R[0]
    states = np.array([state_vector(c, state, R0) for c in cart.reshape(-1, 12)])
    forces = np.array([force_vector(w, c, features) for w, c in zip(wrench, cart.reshape(-1, 12))])

    gaps = int((stamp_ns[-1] - stamp_ns[0]) // period_ns + 1 - len(chosen))
    return dict(states=states, forces=forces, phases=true_phase[1:], dt=period_ns * 1e-9, t=stamp_ns * 1e-9,
                seq=np.array(chosen, dtype=np.int64), skipped=skipped, gaps=gaps, complete=episode.complete,
                problem=episode.problem, path=str(path))


def _sample_period_ns(rate_hz: float) -> int:
    if isinstance(rate_hz, bool) or not isinstance(rate_hz, numbers.Real) or not (
            math.isfinite(rate_hz) and rate_hz > 0):
        raise RecordingError(f"rate_hz must be a positive number, got {rate_hz!r}")
    period = round(1e9 / rate_hz)
    if abs(period - 1e9 / rate_hz) > 1e-3:
        raise RecordingError(f"rate_hz {rate_hz} does not give a whole number of nanoseconds per sample")
    return period


if __name__ == "__main__":
    import sys

    if sys.argv[1:] != ["--writer-process"]:
        sys.exit("python -m services.recording --writer-process: the MCAP writer of an in-process run "
                 "(started by services.recording.WriterProcess, not by hand)")
    # the replies get their own copy of stdout, and stdout itself goes to stderr: a stray
    # print in this process must not corrupt the pickled replies
    replies = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    _writer_main(sys.stdin.buffer, replies)


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
        seqs = [int(m.group(1)) for msg in ep.messages if msg.topic == "/robot/state"
                for m in [SEQ_PREFIX.match(msg.payload)] if m]
        ranges.append((str(path), min(seqs, default=None), max(seqs, default=None), ep.problem or ""))
    gaps = []
    for (path, _, last, problem), (nxt, first, _, _) in zip(ranges, ranges[1:]):
        missing = first - last - 1 if last is not None and first is not None else None
        gaps.append({"part": path, "last_cycle": last, "next_part": nxt, "next_first_cycle": first,
                     "cycles_missing": missing, "part_problem": problem})
    return gaps
