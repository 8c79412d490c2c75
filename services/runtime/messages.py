"""Every message, defined once.

A ``MessageType`` is the single definition from which the wire encoding (JSON,
UTF-8), the MCAP schema (JSON Schema, which Foxglove plots out of the box) and
the documentation (``docs/messages.md``, ``python -m services.runtime.messages``)
all come.  Every message starts with the header

    seq       int  sequence number (for robot-cycle messages: the FRI cycle it belongs to)
    stamp_ns  int  simulation time, ns
    sent_ns   int  CLOCK_MONOTONIC at publish, ns (one-way latency on one host)

``decode`` checks types, array lengths and finiteness and raises
``MessageError`` naming the field: a service that receives garbage drops the
message and counts it; it never crashes.  ``encode`` refuses NaN and infinity
(JSON has no NaN; a NaN from a sensor must be caught where it appears).

The JSON is written and parsed by orjson (every service encodes or decodes a
few thousand messages a second; orjson takes a quarter to a half of the
standard library's time for these, checks included).  The wire format is the standard
library's: compact separators, the fields in definition order, floats in
their shortest round-trip form (float64 exact both ways; orjson writes an
exponent as ``1e-7`` where Python writes ``1e-07``, the same number).  What
orjson would treat differently falls back to the standard library, so the
behaviour is the old one: orjson writes NaN and infinity as ``null``, so an
output with ``null`` in it is encoded again by ``json`` (which refuses them and
names the field); a payload orjson will not parse (``NaN`` and ``Infinity``
literals, numbers beyond float64) is parsed again by ``json`` to say which field
is bad; a value orjson cannot write (non-string keys in an ``object`` field,
integers beyond 64 bits) is written by ``json``.
"""

from __future__ import annotations

import base64
import json
import math
import re
from dataclasses import dataclass

import orjson

from robot_sim.cycle import FRI_CYCLE_NS

# The estimator's period on simulated time: every tenth FRI cycle, the 100 Hz at which the
# thesis sampled its demonstrations.  The learner's samples and the estimator's updates are
# the same instants (stamps that are multiples of it), so a model learned from recordings
# runs online at the rate it was learned at.
ESTIMATOR_PERIOD_NS = 10 * FRI_CYCLE_NS
# once the commander holds the arm the episode is lost: the robot watches the hold this
# long (its summary says how far the tcp went, how hard it pressed) and ends it with reason
# hold:<reason>; the report says the same
HOLD_WATCH_S = 1.0
ESTIMATOR_STRIDE = ESTIMATOR_PERIOD_NS // FRI_CYCLE_NS  # FRI cycles per estimator update
SAMPLE_RATE_HZ = 1e9 / ESTIMATOR_PERIOD_NS  # the demonstrations' sample rate, Hz


def estimator_instant(stamp_ns: int) -> bool:
    """A stamp the estimator updates at (and the learner samples at)."""
    return stamp_ns % ESTIMATOR_PERIOD_NS == 0


HEADER = (
    ("seq", "int", "sequence number; robot-cycle messages carry the FRI cycle they belong to"),
    ("stamp_ns", "int", "simulation time, ns"),
    ("sent_ns", "int", "CLOCK_MONOTONIC when published, ns"),
)


# every message's JSON begins with its seq (the header's first field, compact separators):
# a reader that needs only the cycle of a message need not parse it
SEQ_PREFIX = re.compile(rb'^\{"seq":(-?\d+)')

# the fallback encoder (see the module's doc): json.dumps with options builds a new one per call
_ENCODER = json.JSONEncoder(allow_nan=False, separators=(",", ":"))
_dumps = orjson.dumps
_loads = orjson.loads
_NULL = b"null"


def dumps(obj) -> bytes:
    """Compact JSON bytes of ``obj``, as ``json`` with ``allow_nan=False`` writes
    it (ValueError on NaN or infinity), through orjson where it writes the same."""
    try:
        data = _dumps(obj)
    except (TypeError, orjson.JSONEncodeError):
        return _ENCODER.encode(obj).encode()
    if _NULL in data:  # NaN and infinity become null in orjson: let json judge (or a real null)
        return _ENCODER.encode(obj).encode()
    return data


def loads(data):
    """``json.loads`` through orjson; what orjson rejects is parsed by ``json``
    (which accepts NaN, Infinity and big numbers and so can say what is wrong).  A payload
    nested past the parser's recursion (a foreign peer's ``[[[[...``, under the size limit)
    raises ``json.JSONDecodeError`` like any other that is not JSON: the stdlib raises
    RecursionError, which the callers' handling of bad payloads would not expect."""
    try:
        return _loads(data)
    except orjson.JSONDecodeError:
        try:
            return json.loads(data)
        except RecursionError:
            raise json.JSONDecodeError("nested too deeply to parse", "", 0) from None


class MessageError(ValueError):
    """A message that does not decode or does not match its definition."""


# the largest payload any receiver parses: the biggest message, an episode summary,
# is ~8 KB; a bigger one is refused unread (a foreign peer must not make a service
# parse megabytes at 1 kHz)
MAX_PAYLOAD_BYTES = 64 * 1024


@dataclass(frozen=True)
class Field:
    name: str
    type: str  # int | float | bool | str | float[N] | float[] | int[N] | str[] | object
    doc: str
    optional: bool = False

    @property
    def length(self) -> int | None:
        if "[" in self.type and not self.type.endswith("[]"):
            return int(self.type[self.type.index("[") + 1 : -1])
        return None

    @property
    def base(self) -> str:
        return self.type.split("[")[0]

    def schema(self) -> dict:
        scalar = {"int": {"type": "integer"}, "float": {"type": "number"}, "bool": {"type": "boolean"},
                  # an object says its properties, if only that there are none in particular:
                  # Foxglove Studio 1.48's schema reader fails on an object without them
                  "str": {"type": "string"}, "object": {"type": "object", "properties": {}}}
        if "[" in self.type:
            out = {"type": "array", "items": scalar[self.base], "description": self.doc}
            if self.length is not None:
                out["minItems"] = out["maxItems"] = self.length
            return out
        return dict(scalar[self.base], description=self.doc)


class MessageType:
    def __init__(self, name: str, topic: str, doc: str, fields: tuple, period_ns: int | None = None):
        self.name = name
        self.topic = topic  # relative to the run prefix etar/<run_id>/
        self.channel = "/" + topic  # its channel's topic in a recording (MCAP)
        self.doc = doc
        self.period_ns = period_ns  # how often it is published, simulated time (None: on events)
        self.fields = tuple(Field(*h) for h in HEADER) + tuple(f if isinstance(f, Field) else Field(*f) for f in fields)
        self._required = [f for f in self.fields if not f.optional]
        self._fast = [(f.name, _fast_check(f)) for f in self.fields]
        fast = _compile_pack(self.fields, self._pack_checked)
        if fast is not None:
            self.pack = fast  # the same contract as the method below, a few microseconds sooner

    # -------------------------------------------------------------- wire

    def encode(self, **values) -> bytes:
        """JSON bytes of one message; every required field must be given."""
        return self.pack(**values)[0]

    def pack(self, **values) -> tuple[bytes, dict]:
        return self._pack_checked(values)

    def _pack_checked(self, values: dict) -> tuple[bytes, dict]:
        """(JSON bytes, the message they decode to): ``decode(raw) == message``, with
        the same types, for values that are Python scalars, strings, numpy arrays and
        scalars, or lists and tuples of Python scalars (arrays become lists of floats,
        tuples lists).  One process can hand the message to its subscribers without
        parsing the bytes again (``services.transport.inproc`` checks it on request)."""
        out = {}
        for f in self.fields:
            if f.name not in values:
                if f.optional:
                    continue
                raise MessageError(f"{self.name}: field '{f.name}' is missing")
            out[f.name] = _plain_value(values[f.name])
        extra = set(values) - {f.name for f in self.fields}
        if extra:
            raise MessageError(f"{self.name}: unknown field(s) {sorted(extra)}")
        try:
            return dumps(out), out
        except ValueError as exc:
            bad = [k for k, v in out.items() if _has_non_finite(v)]
            raise MessageError(f"{self.name}: non-finite value in field(s) {bad} ({exc})") from None

    def decode(self, data: bytes) -> dict:
        """Parse and check one message; raises MessageError naming the field."""
        if len(data) > MAX_PAYLOAD_BYTES:
            raise MessageError(f"{self.name}: payload of {len(data)} bytes is over the {MAX_PAYLOAD_BYTES} byte limit")
        try:
            msg = loads(data)
        except (UnicodeDecodeError, json.JSONDecodeError, TypeError) as exc:
            raise MessageError(f"{self.name}: not JSON ({exc})") from None
        if not isinstance(msg, dict):
            raise MessageError(f"{self.name}: expected a JSON object, got {type(msg).__name__}")
        for f in self._required:
            if f.name not in msg:
                raise MessageError(f"{self.name}: field '{f.name}' is missing")
        # every service decodes every message it receives at 1 kHz: the common case
        # (the right types, finite) is settled per field in one step, and only a field
        # that fails it is looked at element by element to name the problem
        for f, (name, ok) in zip(self.fields, self._fast):
            v = msg.get(name, _ABSENT)
            if v is not _ABSENT and not ok(v):
                _check(self.name, f, v)
        return msg

    # ---------------------------------------------------------- schema/doc

    def json_schema(self) -> dict:
        return {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": self.name,
            "description": self.doc,
            "type": "object",
            "properties": {f.name: f.schema() for f in self.fields},
            "required": [f.name for f in self._required],
        }

    def markdown(self) -> str:
        rate = f"Every {self.period_ns / 1e6:g} ms of simulated time." if self.period_ns else "On events."
        lines = [f"### `{self.name}` — `etar/<run_id>/{self.topic}`", "", self.doc, "", rate, "",
                 "| field | type | meaning |", "|---|---|---|"]
        for f in self.fields:
            lines.append(f"| `{f.name}` | `{f.type}`{' (optional)' if f.optional else ''} | {f.doc} |")
        return "\n".join(lines)


_ABSENT = object()
_PLAIN = frozenset({int, float, bool, str, list, dict, type(None)})


def _plain_value(v):
    if hasattr(v, "tolist"):
        return v.tolist()
    if type(v) is tuple:
        return list(v)
    return v


def _compile_pack(fields, checked):
    """``pack`` as one generated function of keyword arguments: every message of a
    1 kHz stream is packed, and the general loop over the fields (a lookup and a
    conversion check each) costs several microseconds more.  Anything unusual - a
    field missing or unknown, a value JSON cannot hold - goes to ``checked``, the
    general path, which names the problem (and leaves out an optional field not given)."""
    names = [f.name for f in fields]
    missing = " or ".join(f"{n} is M" for n in names)
    body = ", ".join(f"{n!r}: {n} if type({n}) in P else C({n})" for n in names)
    src = (f"def pack(*, {', '.join(f'{n}=M' for n in names)}, **extra):\n"
           f"    if extra or {missing}:\n"
           f"        return checked({{k: v for k, v in dict({', '.join(f'{n}={n}' for n in names)}, **extra).items()"
           f" if v is not M}})\n"
           f"    out = {{{body}}}\n"
           f"    try:\n"
           f"        return dumps(out), out\n"
           f"    except ValueError:\n"
           f"        return checked(out)\n")
    scope = {"P": _PLAIN, "C": _plain_value, "M": _ABSENT, "dumps": dumps, "checked": checked}
    exec(src, scope)  # noqa: S102  (names come from the message definitions above, not from input)
    return scope["pack"]

_isfinite = math.isfinite
# the wire's integers are 64-bit (stamps in ns, sequence numbers, counts): JSON's have no
# bound, and a reader's numpy arrays of them would overflow
INT_MIN, INT_MAX = -(2**63), 2**63 - 1


def _fast_check(f: Field):
    """A predicate that is True when the value certainly passes ``_check`` for ``f``
    (False means: look closer, it may still pass, e.g. an int in a float array)."""
    scalar = {"int": int, "float": float, "bool": bool, "str": str, "object": dict}[f.base]
    lo, hi = INT_MIN, INT_MAX
    if "[" not in f.type:
        if scalar is float:
            return lambda v: type(v) is float and _isfinite(v)
        if scalar is int:
            return lambda v: type(v) is int and lo <= v <= hi
        if scalar is dict:
            return lambda v: type(v) is dict and not _has_non_finite(v)
        return lambda v: type(v) is scalar
    n = f.length
    if scalar is float:
        # a sum of finite floats is finite unless it overflows (then the slow path decides)
        return lambda v: (type(v) is list and (n is None or len(v) == n)
                          and all(type(x) is float for x in v) and _isfinite(sum(v)))
    if scalar is int:
        return lambda v: (type(v) is list and (n is None or len(v) == n)
                          and all(type(x) is int and lo <= x <= hi for x in v))
    return lambda v: type(v) is list and (n is None or len(v) == n) and all(type(x) is scalar for x in v)


def _has_non_finite(v) -> bool:
    if isinstance(v, float):
        return not math.isfinite(v)
    if isinstance(v, (list, tuple)):
        return any(_has_non_finite(x) for x in v)
    if isinstance(v, dict):
        return any(_has_non_finite(x) for x in v.values())
    return False


def _check(msg_name: str, f: Field, v) -> None:
    where = f"{msg_name}: field '{f.name}'"
    if "[" in f.type:
        if not isinstance(v, list):
            raise MessageError(f"{where} must be a list, got {type(v).__name__}")
        if f.length is not None and len(v) != f.length:
            raise MessageError(f"{where} must have {f.length} entries, got {len(v)}")
        for i, x in enumerate(v):
            _check_scalar(f"{where}[{i}]", f.base, x)
    else:
        _check_scalar(where, f.base, v)


def _check_scalar(where: str, base: str, x) -> None:
    if base == "int":
        if isinstance(x, bool) or not isinstance(x, int):
            raise MessageError(f"{where} must be an integer, got {x!r}")
        if not INT_MIN <= x <= INT_MAX:
            raise MessageError(f"{where} is an integer of {len(str(abs(x)))} digits, outside 64 bits")
    elif base == "float":
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise MessageError(f"{where} must be a number, got {x!r}")
        if isinstance(x, int) and not INT_MIN <= x <= INT_MAX:
            # JSON's integers have no bound (1 and 400 zeros is valid JSON, past float64 too), and
            # past 64 bits the parser gives a float back: the message would not read as written
            raise MessageError(f"{where} is an integer of {len(str(abs(x)))} digits, past 64 bits "
                               f"(write it as a float)")
        if not math.isfinite(x):
            raise MessageError(f"{where} is {x!r}")
    elif base == "bool":
        if not isinstance(x, bool):
            raise MessageError(f"{where} must be true or false, got {x!r}")
    elif base == "str":
        if not isinstance(x, str):
            raise MessageError(f"{where} must be a string, got {x!r}")
    elif base == "object":
        if not isinstance(x, dict):
            raise MessageError(f"{where} must be an object, got {x!r}")
        if _has_non_finite(x):  # NaN or Infinity inside (the stdlib parser reads them)
            raise MessageError(f"{where} holds a number that is not finite")


# ---------------------------------------------------------------------------
# the messages
# ---------------------------------------------------------------------------

ROBOT_STATE = MessageType(
    "robot_state", "robot/state",
    "FRI measurement packet of one KRC cycle (1 kHz): sent at the start of the cycle; the "
    "impedance commander answers it with a robot_command echoing `seq`.",
    (
        ("reflected_seq", "int", "seq of the last command packet the KRC received (-1: none)"),
        ("fri_state", "int", "FRI state: 0 OFF, 1 MON, 2 CMD"),
        ("fri_quality", "int", "FRI quality: 0 UNACCEPTABLE, 1 BAD, 2 OK, 3 PERFECT"),
        ("control_mode", "int", "1 POSITION, 2 CART_IMP, 3 JNT_IMP"),
        ("msr_jnt_pos", "float[7]", "measured joint positions, rad"),
        ("msr_cart_pos", "float[12]", "measured tcp pose, 3x4 row-major [R | p], base frame, m"),
        ("est_ext_tcp_ft", "float[6]", "estimated external wrench at the tcp [Fx Fy Fz Tz Ty Tx], tcp frame"),
        ("answer_rate", "float", "answered cycles over the last 100"),
        ("latency_s", "float", "mean answer latency over the last 100 cycles, s"),
        ("jitter_s", "float", "standard deviation of the answer latency, s"),
        ("miss_rate", "float", "missed cycles over the last 100"),
        ("safety", "int", "KRC safety stop: 0 none, 1 joint limit, 2 Cartesian force, 3 torque saturation, 4 non-finite"),
        ("gravity_compensation", "bool", "the KRC runs gravity compensation (kinesthetic teaching)"),
        ("episode", "int", "demonstration/reproduction index (-1: none)"),
    ),
    period_ns=FRI_CYCLE_NS,
)

ROBOT_CONTACT = MessageType(
    "robot_contact", "robot/contact",
    "The physics' truth for the cycle: the wrench the tool transmits to the F/T sensor (what the ATI "
    "model samples), the contact force on the tip, the true phase label and the tool's true pose and "
    "velocity (what the teacher's hand, holding the tool, feels).",
    (
        ("wrench", "float[6]", "[Fx Fy Fz Tx Ty Tz] the tool exerts on the sensor, sensor frame, N / N m"),
        ("contact_force", "float[3]", "force the environment exerts on the tip, base frame, N"),
        ("touching", "str[]", "geoms the tip touches"),
        ("true_phase", "int", "physical phase label (valley: 0 free, 1 plate, 2 groove; coupler: 0 approach, 1 coupling)"),
        # optional: recordings made before the teacher felt the tool's true motion lack them
        Field("tcp_pose", "float[12]", "true tcp pose, 3x4 row-major [R | p], base frame, m (what a hand on the "
              "tool feels)", optional=True),
        Field("tcp_twist", "float[6]", "true tcp velocity [vx vy vz wx wy wz], base frame axes, m/s and rad/s",
              optional=True),
        ("episode", "int", "demonstration/reproduction index"),
    ),
    period_ns=FRI_CYCLE_NS,
)

FT_WRENCH = MessageType(
    "ft_wrench", "ft/wrench",
    "ATI Net F/T RDT-like record, sampled once per robot cycle.",
    (
        ("rdt_sequence", "int", "RDT packet counter (gaps: lost packets)"),
        ("ft_sequence", "int", "internal sample counter"),
        ("status", "int", "status bits (0: ok; see robot_sim.ati.rdt.AtiStatus)"),
        ("counts", "int[6]", "Fx Fy Fz Tx Ty Tz in counts"),
        ("counts_per_force", "float", "counts per N"),
        ("counts_per_torque", "float", "counts per N m"),
        ("wrench", "float[6]", "counts converted: [Fx Fy Fz Tx Ty Tz], sensor frame, N / N m"),
    ),
    period_ns=FRI_CYCLE_NS,
)

TEACHER_WRENCH = MessageType(
    "teacher_wrench", "teacher/wrench",
    "The simulated teacher's hand wrench on the flange for robot cycle `seq` (world axes).",
    (
        ("wrench", "float[6]", "[Fx Fy Fz Tx Ty Tz], base axes, N / N m"),
        ("script_phase", "int", "where the teacher's script is"),
        ("done", "bool", "the demonstration is complete"),
        ("episode", "int", "demonstration index"),
    ),
    period_ns=FRI_CYCLE_NS,
)

ESTIMATOR_PHASE = MessageType(
    "estimator_phase", "estimator/phase",
    "Online ETAR forward filter output (100 Hz): p(phase | inputs so far).",
    (
        ("posterior", "float[]", "normalised forward message, one entry per phase"),
        ("phase", "int", "most likely phase"),
        ("input_seq", "int", "robot cycle of the newest state used"),
        ("ft_seq", "int", "robot cycle of the newest wrench used"),
        ("episode", "int", "reproduction index"),
        Field("input_fault", "str", "present when this cycle's wrench could not be used: 'wrench_saturated' "
                                    "or 'wrench_invalid' (the sensor's status bits); the filter was not "
                                    "updated and posterior/phase are the last ones", optional=True),
        Field("unconditioned", "str", "present when the filter took this sample without conditioning on the "
                                      "step that ends at it: 'arm_held' (the KRC was not in command mode at one "
                                      "of its ends, so the phase's law did not drive the arm) or 'gap' (the "
                                      "step's first sample is missing); posterior/phase are the last ones",
              optional=True),
    ),
    period_ns=ESTIMATOR_PERIOD_NS,
)

ROBOT_COMMAND = MessageType(
    "robot_command", "robot/command",
    "FRI command packet: the answer to robot_state `seq` (the echo).",
    (
        ("cart_pos", "float[12]", "commanded tcp pose, 3x4 row-major, base frame"),
        ("cart_stiffness", "float[6]", "[N/m x3, N m/rad x3] along tcp axes"),
        ("cart_damping", "float[6]", "normalised damping 0..1"),
        ("add_tcp_ft", "float[6]", "superposed wrench [Fx Fy Fz Tz Ty Tx], tcp frame"),
        ("requested_mode", "int", "control mode this command is for (2 CART_IMP)"),
        ("phase", "int", "phase whose impedance law made this command's force: the estimate's, or the phase the "
                         "demonstrations went on to while the estimate's is blocked (-1: none, the arm held)"),
        ("estimate_seq", "int", "robot cycle of the phase estimate this command used (-1: none)"),
        ("goal_reached", "bool", "the commander judges the task complete"),
        ("hold", "str", "why the commander holds the arm stiffly where it was instead of following "
                        "the task ('': it does not; 'stale_estimate': no phase estimate for "
                        "STALE_ESTIMATE_CYCLES cycles; 'wrench_saturated', 'wrench_invalid': the estimate "
                        "says its wrench could not be used)"),
        ("episode", "int", "reproduction index"),
    ),
    period_ns=FRI_CYCLE_NS,
)

RUNNER_EVENT = MessageType(
    "runner_event", "runner/event",
    "Stage and episode control from the scenario runner.",
    (
        ("event", "str", "stage_begin | stage_end | episode_begin | episode_end | run_end"),
        ("stage", "str", "demonstrate | learn | reproduce"),
        ("episode", "int", "episode index within the stage (-1: none)"),
        ("info", "object", "anything else (start pose, seeds, ...)"),
    ),
)

EPISODE_SUMMARY = MessageType(
    "episode_summary", "robot/episode",
    "Published by the robot when an episode (demonstration or reproduction) ends.",
    (
        ("episode", "int", "episode index"),
        ("kind", "str", "demonstration | reproduction | served (etar-bench serve: a lab's FRI remote)"),
        ("reason", "str", "why it ended: teacher_done | goal_reached | timeout | elapsed (ran its whole time with "
                           "nothing to stop on) | safety:<reason> (e.g. safety:joint_limit) | hold:<reason> "
                           "(the commander held the arm for HOLD_WATCH_S in one) | stopped"),
        ("first_seq", "int", "first robot cycle of the episode"),
        ("last_seq", "int", "last robot cycle of the episode"),
        ("sim_seconds", "float", "simulated duration, s"),
        ("wall_seconds", "float", "wall-clock duration, s"),
        ("final_position", "float[3]", "tcp position at the end, m"),
        ("peak_contact_force", "float", "largest contact force on the tip during the episode, N"),
        ("safety", "int", "KRC safety state at the end (0: none)"),
        ("missed_answers", "int", "lockstep: cycles whose awaited answers did not come in time"),
        Field("goal_reached_at_s", "float", "simulated time into the episode when the commander first reported "
                                            "the goal reached (-1: never)", optional=True),
        Field("hold", "object", "if the commander held the arm: reason, seq and at_s of its first hold "
                                "command, estimate_seq (the last estimate it had), cycles held in all, and "
                                "what the robot measured while held: max_displacement_m of the tcp (from "
                                "where each hold began), peak_contact_force",
              optional=True),
        ("fri", "object", "FRI link statistics of this episode (counts) and at its end (state, quality)"),
        ("loop", "object", "timing statistics of the robot's 1 kHz loop"),
        Field("wire", "object", "--wire udp: the KRC's and the remote's addresses, the KRL convention, the "
                                "datagrams (sent, received, accepted, late, duplicate, wrong_size, wrong_id, "
                                "invalid, foreign: from another sender than the remote, ...), the KRL program's events, the link's state changes, seconds "
                                "in command mode, first commands refused, the last refusal", optional=True),
    ),
)

FRI_DATAGRAM = MessageType(
    "fri_datagram", "fri/datagram",
    "An FRI 1.0 datagram that crossed the KRC's UDP socket (`--wire udp`, `etar-bench serve`), the bytes "
    "as they went and their fields decoded: each cycle's measurement, and the command that answered it "
    "in time (one the KRC accepted).  `seq` is the cycle (the full count: the header's counters are its "
    "low 16 bits); `sent_ns`: when the measurement was sent, or the command read.",
    (
        ("direction", "str", "measurement (KRC -> remote, 916 bytes) | command (remote -> KRC, 376 bytes)"),
        ("bytes", "str", "the datagram, base64 (docs/fri.md gives every field's offset)"),
        ("decoded", "object", "its fields with FRI's names, nested as FRI nests them: head, krl, intf, robot, "
                              "data (measurement); head, krl, cmd (command); float32 values as float64"),
    ),
)

NETFT_RDT = MessageType(
    "netft_rdt", "netft/rdt",
    "An RDT datagram the simulated Net F/T box sent to a streaming client (`--netft`), the bytes as they "
    "went and its records decoded.  `seq`/`stamp_ns`: the robot cycle of the (last) record in it.",
    (
        ("client", "str", "HOST:PORT of the client it went to"),
        ("bytes", "str", "the datagram, base64: one 36-byte record, or several (buffered streaming)"),
        ("records", "object[]", "each record: rdt_sequence, ft_sequence, status (Net F/T bits), counts "
                                "[Fx Fy Fz Tx Ty Tz] (big-endian int32 on the wire)"),
    ),
)

SERVICE_LOG = MessageType(
    "service_log", "service/log",
    "A line a service logged (its stderr has it too): recorded with the episode it falls in, "
    "and a foxglove.Log line in the visual topics.  `stamp_ns` is 0: a service's log has no "
    "simulation time; `seq` counts the service's lines.",
    (
        ("role", "str", "the service that logged it"),
        ("level", "int", "2 INFO, 3 WARNING, 4 ERROR (foxglove.LogLevel)"),
        ("text", "str", "the line"),
    ),
)

MESSAGES = {m.name: m for m in (ROBOT_STATE, ROBOT_CONTACT, FT_WRENCH, TEACHER_WRENCH, ESTIMATOR_PHASE,
                                ROBOT_COMMAND, RUNNER_EVENT, EPISODE_SUMMARY, FRI_DATAGRAM, NETFT_RDT,
                                SERVICE_LOG)}
BY_TOPIC = {m.topic: m for m in MESSAGES.values()}
# topics published every n-th FRI cycle: their seq counts FRI cycles, so it advances by n
STRIDES = {m.topic: m.period_ns // FRI_CYCLE_NS for m in MESSAGES.values()
           if m.period_ns is not None and m.period_ns > FRI_CYCLE_NS}


def datagram_fields(data: bytes, direction: str) -> dict:
    """FRI_DATAGRAM's ``bytes`` and ``decoded`` for the datagram ``data``."""
    # here, not at the top: the datagrams' decoders bring the FRI link's compiled kernels (numba), which a
    # process that only carries or records messages never needs
    from robot_sim.wire.fri_datagrams import decode_command, decode_measurement, record_fields

    record = decode_measurement(data) if direction == "measurement" else decode_command(data)
    return {"bytes": base64.b64encode(data).decode("ascii"), "decoded": _finite_or_none(record_fields(record))}


def _finite_or_none(value):
    """JSON has no NaN: a field a command leaves unflagged may hold any float32, which
    the bytes keep; decoded, a non-finite one is null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, list):
        return [_finite_or_none(v) for v in value]
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    return value


def documentation() -> str:
    parts = ["# Messages", "", "Generated from `services/runtime/messages.py` "
             "(`python -m services.runtime.messages > docs/messages.md`).", "",
             "All key expressions live under `etar/<run_id>/`.  Encoding: JSON (UTF-8); MCAP schema: "
             "JSON Schema (draft 2020-12).", ""]
    for m in MESSAGES.values():
        parts += [m.markdown(), ""]
    return "\n".join(parts)


if __name__ == "__main__":
    print(documentation())
