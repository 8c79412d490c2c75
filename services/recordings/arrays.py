"""A recording as numpy arrays, for notebooks: one array per field of a topic's messages.

``topic_arrays(path, "/robot/state")`` reads the file once (``read_episode``, so a
truncated recording gives what it recovered, with a ``TruncatedRecordingWarning`` that
says so) and returns, in log-time order, one array
per field, first axis the message:

- ``log_time_ns`` and ``publish_time_ns`` (int64): the recorder's receive time and the
  sender's ``sent_ns`` (``format``), beside the message's own fields;
- a field of a message type of ``services.runtime.messages`` takes its declared type:
  ``float`` float64, ``int`` int64 (``seq``, ``stamp_ns``, ``sent_ns`` stay exact),
  ``bool`` bool, ``str`` a numpy string array; a list field (``float[12]``, ``int[6]``)
  a 2-D array (messages, entries), one of varying length (``float[]``, e.g. the
  estimator's posterior) padded with NaN to the longest; ``str[]`` an object array of
  lists;
- an ``object`` field (``fri``, ``loop``, ``info``) and every field of a topic without a
  definition (the visual topics, ``/viz/...``) are flattened into dotted names
  (``fri.answered``, ``timestamp.sec``), their types read from the values: integers
  int64 (float64 with NaN where a message lacks the field), numbers float64, equal-length
  numeric lists 2-D (ragged ones NaN-padded), anything else an object array.

A payload that does not decode (or, for a defined type, does not match its definition)
raises ``RecordingError`` naming the file, the topic and the message;
``skip_bad=True`` leaves such messages out.  ``topic_frame`` gives the same as a
pandas DataFrame (2-D fields as columns ``name[i]``) where pandas is installed; pandas
is not a dependency of the testbench.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from services.recordings.format import RecordingError
from services.recordings.reader import RecordedMessage, read_episode
from services.runtime.messages import BY_TOPIC, MessageError, MessageType, loads

# the two times every message has in the file, beside its payload's fields
TIME_FIELDS = ("log_time_ns", "publish_time_ns")
_MISSING = object()


class TruncatedRecordingWarning(UserWarning):
    """The arrays come from a recording that was not finished (its complete chunks only)."""


def _read(path):
    episode = read_episode(path)
    if not episode.complete:
        warnings.warn(f"{episode.path}: a truncated recording ({episode.problem or 'not finished'}): the arrays hold "
                      f"the {len(episode.messages)} messages of its complete chunks", TruncatedRecordingWarning,
                      stacklevel=3)
    return episode


def topic_arrays(path, topic: str, *, skip_bad: bool = False) -> dict[str, np.ndarray]:
    """Every message of ``topic`` (``"/robot/state"`` or ``"robot/state"``) in the recording
    at ``path`` as {field: array}, first axis the message (module docstring).  A topic the
    file has no channel for raises ``RecordingError`` naming the topics it has."""
    episode = _read(path)
    name = _topic_name(topic)
    if name not in episode.channels and not any(m.topic == name for m in episode.messages):
        have = ", ".join(sorted(episode.channels)) or "none"
        raise RecordingError(f"{episode.path}: no topic {name!r} in this recording (topics: {have})")
    return _arrays(episode.path, name, [m for m in episode.messages if m.topic == name], skip_bad)


def recording_arrays(path, *, skip_bad: bool = False, topics=None) -> dict[str, dict[str, np.ndarray]]:
    """``topic_arrays`` of every topic of the recording at ``path`` (or of those of
    ``topics`` it has), reading it once: {topic: {field: array}}, topics sorted."""
    episode = _read(path)
    wanted = None if topics is None else {_topic_name(t) for t in topics}
    by_topic: dict[str, list[RecordedMessage]] = {t: [] for t in episode.channels if wanted is None or t in wanted}
    for m in episode.messages:
        if wanted is None or m.topic in wanted:
            by_topic.setdefault(m.topic, []).append(m)
    return {t: _arrays(episode.path, t, by_topic[t], skip_bad) for t in sorted(by_topic)}


def topic_frame(path, topic: str, *, skip_bad: bool = False):
    """``topic_arrays`` as a pandas DataFrame, one row per message: a 2-D field becomes
    columns ``name[0]``, ``name[1]``, ...; ImportError if pandas is not installed."""
    try:
        import pandas
    except ImportError:
        raise ImportError("topic_frame needs pandas, which the testbench does not install: pip install pandas "
                          "(or use topic_arrays, the same data as numpy arrays)") from None
    columns = {}
    for name, values in topic_arrays(path, topic, skip_bad=skip_bad).items():
        if values.ndim == 2:
            for i in range(values.shape[1]):
                columns[f"{name}[{i}]"] = values[:, i]
        elif values.ndim > 2:
            columns[name] = list(values)  # one array per row
        else:
            columns[name] = values
    return pandas.DataFrame(columns)


# ---------------------------------------------------------------------------


def _topic_name(topic: str) -> str:
    """The recording's name of a topic: with its leading slash (``format``)."""
    if not isinstance(topic, str) or not topic.strip("/"):
        raise ValueError(f"a topic name such as '/robot/state', got {topic!r}")
    return "/" + topic.lstrip("/")


def _arrays(path: Path, topic: str, messages: list[RecordedMessage], skip_bad: bool) -> dict[str, np.ndarray]:
    mtype = BY_TOPIC.get(topic.lstrip("/"))
    rows, times = [], []
    for i, m in enumerate(messages):
        try:
            row = _decode(mtype, m.payload)
        except ValueError as exc:  # MessageError, JSON errors, not an object
            if skip_bad:
                continue
            raise RecordingError(f"{path}: {topic} message {i} (log time {m.log_time_ns} ns) does not decode: "
                                 f"{exc} (topic_arrays(..., skip_bad=True) leaves such messages out)") from None
        rows.append(_flatten(row))
        times.append((m.log_time_ns, m.publish_time_ns))
    out = {name: np.array([t[k] for t in times], dtype=np.int64).reshape(len(times))
           for k, name in enumerate(TIME_FIELDS)}
    declared = {} if mtype is None else {f.name: f for f in mtype.fields if f.base != "object"}
    names = list(declared)  # the definition's order, then what the payloads add
    for row in rows:
        names.extend(k for k in row if k not in declared and k not in names)
    for name in dict.fromkeys(names):
        values = [row.get(name, _MISSING) for row in rows]
        field = declared.get(name)
        out[name] = _declared_column(values, field) if field is not None else _inferred_column(values)
    return out


def _decode(mtype: MessageType | None, payload: bytes) -> dict:
    if mtype is not None:
        return mtype.decode(payload)
    msg = loads(payload)
    if not isinstance(msg, dict):
        raise MessageError(f"expected a JSON object, got {type(msg).__name__}")
    return msg


def _flatten(msg: dict, prefix: str = "") -> dict:
    """Nested objects as dotted names (a defined type's ``object`` fields among them)."""
    out = {}
    for k, v in msg.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, name + "."))
        else:
            out[name] = v
    return out


def _declared_column(values: list, field) -> np.ndarray:
    n = len(values)
    if field.base == "str" and "[" in field.type:  # str[]: lists of names, e.g. the geoms touched
        return _objects([None if v is _MISSING else list(v) for v in values])
    if "[" in field.type:
        dtype = np.int64 if field.base == "int" and not any(v is _MISSING for v in values) else np.float64
        return _padded(values, dtype, field.length)
    if any(v is _MISSING for v in values):  # an optional field some messages lack
        if field.base in ("int", "float"):
            return np.array([math.nan if v is _MISSING else float(v) for v in values], dtype=np.float64)
        return _objects([None if v is _MISSING else v for v in values])
    dtype = {"float": np.float64, "int": np.int64, "bool": np.bool_, "str": np.str_}[field.base]
    return np.array(values, dtype=dtype).reshape(n)


def _inferred_column(values: list) -> np.ndarray:
    present = [v for v in values if v is not _MISSING]
    complete = len(present) == len(values)
    if present and all(type(v) is bool for v in present) and complete:
        return np.array(values, dtype=np.bool_)
    if present and all(type(v) is int for v in present):
        return np.array(values, dtype=np.int64) if complete else _floats(values)
    if present and all(type(v) in (int, float) for v in present):
        return _floats(values)
    if present and all(type(v) is str for v in present) and complete:
        return np.array(values, dtype=np.str_)
    if present and all(type(v) is list and all(type(x) in (int, float) for x in v) for v in present):
        ints = all(type(x) is int for v in present for x in v)
        lengths = {len(v) for v in present}
        dtype = np.int64 if ints and complete and len(lengths) == 1 else np.float64
        return _padded(values, dtype, None)
    return _objects([None if v is _MISSING else v for v in values])


def _floats(values: list) -> np.ndarray:
    return np.array([math.nan if v is _MISSING else float(v) for v in values], dtype=np.float64)


def _padded(values: list, dtype, length: int | None) -> np.ndarray:
    """Lists as a (messages, entries) array; shorter or missing rows padded with NaN."""
    width = length if length is not None else max((len(v) for v in values if v is not _MISSING), default=0)
    if dtype is np.int64:
        return np.array(values, dtype=np.int64).reshape(len(values), width)
    out = np.full((len(values), width), math.nan)
    for i, v in enumerate(values):
        if v is not _MISSING and len(v):
            out[i, :len(v)] = v
    return out


def _objects(values: list) -> np.ndarray:
    out = np.empty(len(values), dtype=object)
    for i, v in enumerate(values):  # element-wise: numpy must not turn equal-length lists into 2-D
        out[i] = v
    return out
