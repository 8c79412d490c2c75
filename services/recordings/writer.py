"""Writing a recording: ``EpisodeWriter``, a narrow format object over ``mcap.writer.Writer``.

The recorder hands it, per received sample, the key expression, the payload bytes
and the receive time; the payload goes into the file unchanged (``format``).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, IndexType, Writer

from services.recordings.format import CHUNK_SIZE, METADATA_NAME, SCENARIO_ATTACHMENT, SCENARIO_MEDIA_TYPE, RecordingError
from services.runtime.provenance import code, code_text
from services.runtime.messages import BY_TOPIC, MessageError, MessageType, loads
from services.runtime.visual_topics import DERIVED_BY, SCHEMA_NAMES as VISUAL_SCHEMA_NAMES, schema_bytes as visual_schema

_GENERIC_SCHEMA_NAME = "json_object"
_UINT64 = 2**64


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
        self._failure: str | None = None  # why the file cannot take more (a full disk)

        record = {"run_id": run_id, "episode_kind": str(episode_kind), "episode_index": str(int(episode_index)),
                  "log_time": "CLOCK_MONOTONIC ns at reception (recorder)",
                  "publish_time": "sent_ns header, CLOCK_MONOTONIC ns (log time if the payload does not decode)",
                  # the code that wrote the file (etar-bench info shows it)
                  **{f"code_{k}": str(v) for k, v in code().items()}}
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
            # the library string names the code too, for readers that show only the header
            self._writer.start(profile="", library=f"etar-testbench {code_text()} services.recordings; "
                                                   f"{LIBRARY_IDENTIFIER}")
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
            if self._failure is not None:
                raise RecordingError(self._failure)
            entry = self._channels.get(key_expr)
            if entry is None:
                try:
                    entry = self._register(key_expr)
                except OSError as exc:
                    raise self._failed_with(exc) from None
            channel_id, mtype = entry
            if publish_time_ns is None:
                sent = self._sent_ns(mtype, data)
                publish_time_ns = log_time_ns if sent is None else sent
            try:
                self._writer.add_message(channel_id=channel_id, log_time=log_time_ns, data=data,
                                         publish_time=publish_time_ns)
            except OSError as exc:
                raise self._failed_with(exc) from None
            self.messages_written += 1

    def _sent_ns(self, mtype: MessageType | None, data: bytes) -> int | None:
        try:
            if mtype is not None:
                msg = mtype.decode(data)
            else:
                msg = loads(data)
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
        """A visual topic (services.runtime.visual_topics): derived by the recorder, not received, so under
        its own name (/viz/...) with Foxglove's schema, beside the run's topics."""
        name = VISUAL_SCHEMA_NAMES[topic]
        schema_id = self._schemas.get(name)
        if schema_id is None:
            schema_id = self._writer.register_schema(name=name, encoding="jsonschema", data=visual_schema(topic))
            self._schemas[name] = schema_id
        channel_id = self._writer.register_channel(topic=topic, message_encoding="json", schema_id=schema_id,
                                                   metadata={"derived_by": DERIVED_BY})
        self._channels[topic] = (channel_id, None)
        return channel_id, None

    # -------------------------------------------------------------- lifetime

    def finish(self) -> None:
        """Write the last chunk and the summary, and close the file.  Idempotent."""
        with self._lock:
            if self._finished:
                return
            self._finished = True
            if self._failure is None:
                try:
                    self._writer.finish()
                except OSError as exc:
                    self._failed_with(exc)
            try:
                self._file.close()
            except OSError as exc:  # the last buffered bytes, on a full disk
                if self._failure is None:
                    self._failed_with(exc)
            if self._failure is not None:
                raise RecordingError(self._failure)

    def _failed_with(self, exc: OSError) -> RecordingError:
        """The file cannot take more (a full disk): said once, naming it and the space left;
        nothing more is written to it, and what it holds stays readable."""
        from services.runtime.files import free_space

        self._failure = (f"{self.path}: could not be written ({exc.strerror or exc}; {free_space(self.path)}); it "
                         "keeps its complete chunks (etar-bench recover makes it a finished file)")
        return RecordingError(self._failure)

    @property
    def finished(self) -> bool:
        return self._finished

    def __enter__(self) -> EpisodeWriter:
        return self

    def __exit__(self, *exc) -> None:
        # finish even on error: whatever was recorded stays readable
        self.finish()


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
            "type": "object", "properties": {}}

