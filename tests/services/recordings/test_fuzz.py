"""Property-based fuzzing (hypothesis) of every reader of what crosses the wire or the
disk: the message decoders, the report's reader of recorded episodes, the recording
reader.  Each gets 10^4 cases, derandomised (the same cases every run) and without an
example database, so a failure reproduces from the code alone.

The cases are random bytes, and (mostly) JSON objects shaped like the message: its
field names, each holding either a valid value or a random JSON value (NaN,
infinities, huge integers, wrong types, wrong lengths, nested junk), some fields
missing, some extra.  A decoder must either raise ``MessageError`` or return a
message that encodes again (``pack`` checks every field, finiteness included)."""

import json
import tempfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.results import decoding, report
from services.recordings.writer import EpisodeWriter
from services.recordings.reader import RecordedMessage, read_episode
from services.recordings.format import RecordingError
from services.runtime.messages import MAX_PAYLOAD_BYTES, MESSAGES, MessageError

CASES = int(__import__("os").environ.get("FUZZ_CASES", 10_000))
FUZZ = settings(max_examples=CASES, derandomize=True, database=None, deadline=None,
                suppress_health_check=list(HealthCheck))

# JSON's integers have no bound: one past float64's range must be refused, not overflow
scalars = (st.none() | st.booleans() | st.integers() | st.integers(min_value=-2**70, max_value=2**70)
           | st.sampled_from([10**400, -(10**400)])
           | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=4))
junk = scalars | st.lists(scalars, max_size=13) | st.dictionaries(st.text(max_size=3), scalars, max_size=2)


def valid_message(mtype, rng) -> dict:
    """One valid message of the type, its values from ``rng``."""
    def value(f):
        one = {"int": lambda: int(rng.integers(-1000, 10**9)), "float": lambda: float(rng.normal()),
               "bool": lambda: bool(rng.integers(2)), "str": lambda: "x" * int(rng.integers(4)),
               "object": lambda: {"k": float(rng.normal())}}[f.base]
        if "[" not in f.type:
            return one()
        return [one() for _ in range(f.length if f.length is not None else int(rng.integers(4)))]

    return {f.name: value(f) for f in mtype.fields}


REMOVE = "<remove this field>"
TYPES = [MESSAGES[n] for n in sorted(MESSAGES)]
BASES = {m.name: valid_message(m, np.random.default_rng(0)) for m in TYPES}
WHOLE = {name: json.dumps(base).encode() for name, base in BASES.items()}

# one case: how to damage a valid message, the same way for every type (a field is
# picked by its index modulo the type's field count)
mutation = st.tuples(st.integers(0, 63), st.one_of(junk, st.just(REMOVE)))
case = st.one_of(
    st.tuples(st.just("json"), st.lists(mutation, min_size=1, max_size=3)),
    st.tuples(st.just("json"), st.lists(mutation, min_size=1, max_size=3)),
    st.tuples(st.just("json"), st.lists(mutation, min_size=1, max_size=3)),
    st.tuples(st.just("bytes"), st.binary(max_size=200)),
    st.tuples(st.just("cut"), st.floats(0, 1)),
)
# every example draws this many cases, each applied to every reader: 10^4 cases per
# reader from 10^3 examples (hypothesis costs ~1 ms an example here, whatever it draws)
PER_EXAMPLE = 10
EXAMPLES = max(1, CASES // PER_EXAMPLE)
FUZZ = settings(FUZZ, max_examples=EXAMPLES)


def payload(mtype, spec) -> bytes:
    kind, arg = spec
    if kind == "bytes":
        return arg
    if kind == "cut":
        whole = WHOLE[mtype.name]
        return whole[: int(arg * (len(whole) - 1))]
    d = dict(BASES[mtype.name])
    names = [f.name for f in mtype.fields] + ["extra"]
    for index, value in arg:
        name = names[index % len(names)]
        if value == REMOVE:
            d.pop(name, None)
        else:
            d[name] = value
    return json.dumps(d, allow_nan=True).encode()


@pytest.mark.slow
@FUZZ
@given(st.lists(case, min_size=PER_EXAMPLE, max_size=PER_EXAMPLE))
def test_every_decoder_raises_message_error_or_returns_a_message_that_encodes_again(cases):
    for spec in cases:
        for mtype in TYPES:
            raw = payload(mtype, spec)
            try:
                msg = mtype.decode(raw)
            except MessageError:
                continue
            # what a decoder lets through is a message: every field present, right types, finite
            fields = {f.name: msg[f.name] for f in mtype.fields if f.name in msg}
            again, _ = mtype.pack(**fields)
            assert mtype.decode(again) == fields


@pytest.mark.slow
@FUZZ
@given(st.lists(case, min_size=PER_EXAMPLE, max_size=PER_EXAMPLE))
def test_the_report_reads_any_recorded_episode_without_failing(cases):
    """Each case an episode with one message of every type on its topic (the same
    damage to each), through everything the report computes from a recording."""
    for spec in cases:
        ep = SimpleNamespace(messages=[RecordedMessage("/" + m.topic, k * 1_000_000, payload(m, spec), k)
                                       for k, m in enumerate(TYPES)])
        decoded, bad = decoding.decoded_messages(ep)
        assert bad + sum(len(v) for v in decoded.values()) == len(ep.messages)
        for items in decoded.values():
            for _, values in items:
                assert all(type(v) is int for v in values.values())
        decoding.episode_links(decoded)
        assert decoding.reproduction_phases(decoded, {"0": 0, "1": 1, "2": 2})["updates"] >= 0
        timeline = report.fri_quality_timeline(*decoding.fri_quality_series(decoded))
        assert timeline["cycles"] == len(decoded.get("robot/state", ()))


def test_a_decoder_refuses_an_oversized_payload_unread():
    mtype = MESSAGES["robot_state"]
    with pytest.raises(MessageError, match="byte limit"):
        mtype.decode(b" " * (MAX_PAYLOAD_BYTES + 1))


def _small_recording() -> bytes:
    path = Path(tempfile.mkdtemp()) / "small.mcap"
    with EpisodeWriter(path, run_id="fuzz", episode_kind="demonstration", episode_index=0,
                       scenario_text="name: fuzz\n") as w:
        for seq in range(1, 40):
            w.add("etar/fuzz/robot/contact", MESSAGES["robot_contact"].encode(
                seq=seq, stamp_ns=seq * 1_000_000, sent_ns=seq, wrench=np.zeros(6), contact_force=np.zeros(3),
                touching=[], true_phase=0, episode=0), seq * 1_000_000)
    return path.read_bytes()


SMALL = _small_recording()
SCRATCH = Path(tempfile.mkdtemp(dir="/dev/shm" if Path("/dev/shm").is_dir() else None)) / "case.mcap"


# one damage to the small recording: cut at a fraction of it, bytes flipped, bytes
# inserted, a run of bytes zeroed
damage = st.one_of(
    st.tuples(st.just("cut"), st.floats(0, 1), st.just(b"")),
    st.tuples(st.just("flip"), st.lists(st.tuples(st.floats(0, 1), st.integers(1, 255)), min_size=1, max_size=4),
              st.just(b"")),
    st.tuples(st.just("insert"), st.floats(0, 1), st.binary(min_size=1, max_size=16)),
    st.tuples(st.just("zero"), st.floats(0, 1), st.integers(1, 64)),
)


def damaged(spec) -> bytes:
    kind, where, extra = spec
    data = bytearray(SMALL)
    last = len(data) - 1
    if kind == "cut":
        return bytes(data[: int(where * last)])
    if kind == "flip":
        for at, bits in where:
            data[int(at * last)] ^= bits
        return bytes(data)
    at = int(where * last)
    if kind == "insert":
        return bytes(data[:at]) + extra + bytes(data[at:])
    data[at:at + extra] = bytes(len(data[at:at + extra]))
    return bytes(data)


@pytest.mark.slow
@FUZZ
@given(st.lists(damage, min_size=PER_EXAMPLE, max_size=PER_EXAMPLE))
def test_the_recording_reader_returns_what_it_kept_or_raises_recording_error(damages):
    for spec in damages:
        SCRATCH.write_bytes(damaged(spec))
        try:
            ep = read_episode(SCRATCH)
        except RecordingError as exc:
            assert str(SCRATCH) in str(exc)
            continue
        # complete: everything; not: a problem stated, and at most what was written
        assert len(ep.messages) == 39 if ep.complete else (ep.problem and len(ep.messages) <= 39)
        assert all(m.topic == "/robot/contact" for m in ep.messages)


def test_an_integer_too_large_for_a_float_is_a_message_error_naming_the_field():
    """A float field (alone or in an array) holding 1 and 400 zeros, valid JSON: refused
    as every other bad value is (it raised OverflowError, which a subscriber's drain
    thread did not catch: one foreign message silenced the subscription)."""
    checked = 0
    for mtype in TYPES:
        for f in mtype.fields:
            if f.base != "float":
                continue
            d = dict(BASES[mtype.name])
            d[f.name] = [1.0] * (f.length or 1) if "[" in f.type else 1.0
            if "[" in f.type:
                d[f.name][-1] = 10**400
            else:
                d[f.name] = 10**400
            with pytest.raises(MessageError, match=f"field '{f.name}'.*401 digits, past 64 bits"):
                mtype.decode(json.dumps(d).encode())
            checked += 1
    assert checked > 20
