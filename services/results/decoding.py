"""A recorded episode decoded once, for the report and for the figures.

``decode_episode(reading)`` reads one recording (and the further parts of one whose
recorder restarted) and takes from it what the ``EpisodeReading`` asks for:

- the report's measures: per topic the publish -> recorder latency and the messages lost
  or out of order, the FRI quality and state over the episode, the messages it could not
  read, and for a reproduction its online phase estimate scored against the true phase;
- the figures' data: a demonstration as the learner takes it (``demonstration_of``'s
  arrays), a reproduction's trace (its force feature and its estimated, commanded and
  true phases over time).

The run's report asks for both and leaves the figures' data in the run's record, so the
figures drawn after it read no recording again; ``etar-bench figures RUN_DIR`` asks for
the figures' data alone.  Each recording is read once and let go: a valley run's
recordings do not fit in memory together.
"""

from __future__ import annotations

import os
from array import array
from dataclasses import dataclass

import numpy as np

from etar.metrics import score_segmentation
from services.recordings.demonstrations import demonstration_of
from services.recordings.reader import Episode, read_episode
from services.runtime.messages import (BY_TOPIC, ESTIMATOR_PERIOD_NS, ESTIMATOR_PHASE, INT_MAX, INT_MIN,
                                       ROBOT_COMMAND, ROBOT_CONTACT, ROBOT_STATE, STRIDES, loads)
from services.runtime.threads import process_map
from services.runtime.timing import SequenceTracker, on_the_clock, percentiles

# what the report reads of each topic: every one an integer (counts, sequence numbers, clocks, labels)
REPORT_FIELDS = {ROBOT_STATE.topic: ("seq", "sent_ns", "stamp_ns", "fri_quality", "fri_state"),
                 ROBOT_CONTACT.topic: ("seq", "sent_ns", "true_phase"),
                 ESTIMATOR_PHASE.topic: ("seq", "sent_ns", "phase")}
_HEADER = ("seq", "sent_ns")
# optional text fields the report counts, with the values it knows (any other is not read)
REPORT_TEXT = {ESTIMATOR_PHASE.topic: {"unconditioned": ("arm_held", "gap")}}
# the topics a reproduction's trace is taken from
TRACE_TOPICS = (ESTIMATOR_PHASE.channel, ROBOT_COMMAND.channel, ROBOT_CONTACT.channel)

# recordings read at ~15 MB/s in one process: below this, a pool's start costs more than it saves
PARALLEL_READ_BYTES = 32 << 20


@dataclass(frozen=True)
class LearnerView:
    """How the learner takes a demonstration (a model's ``state``, ``features`` and
    ``state_resolution``): the figures' arrays are decoded as the model saw its data."""

    state: str
    features: str
    state_resolution: float = 0.0


@dataclass(frozen=True)
class EpisodeReading:
    """What to take from one recording (``parts``: the further files of an episode whose
    recorder restarted, in order; the report reads them too, the figures the first only)."""

    path: str
    parts: tuple = ()
    measures: bool = True  # the report's measures
    phase_to_truth: dict | None = None  # a reproduction's: its online estimate scored with this mapping
    demonstration: LearnerView | None = None  # the learner's arrays, for the demonstrations' figures
    trace: LearnerView | None = None  # the reproduction's trace, for its figure


@dataclass
class ReproductionTrace:
    """What a reproduction's figure draws: the force feature at the learner's sample
    instants, and in time order the estimator's phases and posteriors, the commander's
    phases and the true phase of each robot cycle."""

    t: np.ndarray  # (T,) s, simulated
    forces: np.ndarray  # (T, 3) N, or (T, 6) N and N m, base axes
    estimates: list  # (stamp s, phase, posterior, the robot cycle it estimated), by stamp
    commanded: list  # (stamp s, phase), in order
    truth_by_seq: dict  # robot cycle -> its true phase (the first message of a cycle)


@dataclass
class FigureData:
    """What the figures draw from one recording: a demonstration's arrays, a
    reproduction's trace, or why there are none (the message says the file)."""

    arrays: dict | None = None
    trace: ReproductionTrace | None = None
    problem: str | None = None
    cut: str | None = None  # drawn from a recording that was not finished: the file and why


@dataclass
class DecodedEpisode:
    """One recording as ``decode_episode`` took it; a measure not asked for is None."""

    path: str
    readable: bool = True  # False: its first file did not read, and there are no measures
    links: dict | None = None  # topic -> latency percentiles, lost, out_of_order, off_clock
    phases: dict | None = None  # a reproduction's online phase scores
    fri_quality: tuple | None = None  # (simulated time s, FRI quality, FRI state) of every robot cycle
    undecodable: int = 0  # messages that did not decode
    figure_data: FigureData | None = None


def decode_episode(reading: EpisodeReading) -> DecodedEpisode:
    """``reading``'s recording decoded once for what it asks (module docstring)."""
    decoded, bad = {}, 0
    out = DecodedEpisode(reading.path)
    for i, part in enumerate([reading.path, *reading.parts]):
        try:
            ep = read_episode(part)
        except (OSError, ValueError) as exc:
            if i == 0:
                out.readable = False
                if reading.demonstration is not None or reading.trace is not None:
                    out.figure_data = FigureData(problem=str(exc))
                return out
            continue
        if i == 0 and (reading.demonstration is not None or reading.trace is not None):
            out.figure_data = _figure_data(ep, reading)
        if not reading.measures:
            return out
        part_decoded, part_bad = decoded_messages(ep)
        del ep
        for topic, items in part_decoded.items():
            if topic in decoded:
                decoded[topic].extend(items)
            else:
                decoded[topic] = items
        bad += part_bad
    out.links, out.fri_quality, out.undecodable = episode_links(decoded), fri_quality_series(decoded), bad
    if reading.phase_to_truth:
        out.phases = reproduction_phases(decoded, reading.phase_to_truth)
    return out


def decode_episodes(readings: list[EpisodeReading], workers: int | None = 1,
                    decoded: list = ()) -> list[DecodedEpisode]:
    """``decode_episode`` of each reading, in order; on ``workers`` processes (None: every
    CPU) once the recordings are worth a pool's start (~1.4 s of imports per process).
    ``decoded``: (reading, its DecodedEpisode) pairs decoded already, while the run went on
    (``services.run.report_reads``): a reading equal to one of them is not decoded again."""
    out = [next((d for r, d in decoded if r == reading), None) for reading in readings]
    todo = [i for i, d in enumerate(out) if d is None]
    rest = [readings[i] for i in todo]
    if recordings_size(rest) < PARALLEL_READ_BYTES:
        workers = 1
    with process_map(workers) as read_map:
        for i, d in zip(todo, read_map(decode_episode, rest)):
            out[i] = d
    return out


def recordings_size(readings) -> int:
    """Bytes on disk of the readings' recordings (their first files; one not there counts 0)."""
    return sum(_size(r.path) for r in readings)


def _size(path) -> int:
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


# ------------------------------------------------------------------ for the figures


def _figure_data(ep: Episode, reading: EpisodeReading) -> FigureData:
    view = reading.demonstration or reading.trace
    try:
        # as the learner takes it; a reproduction's states are not drawn, its forces are
        arrays = demonstration_of(ep, reading.path, state=view.state, features=view.features,
                                  state_resolution=view.state_resolution, allow_incomplete=True)
    except (OSError, ValueError) as exc:
        return FigureData(problem=str(exc))
    # a part cut where the next one goes on (a recorder restarted mid-episode) is cut by design
    cut = None if ep.complete or reading.parts else f"{reading.path}: {ep.problem or 'not finished'}"
    if reading.demonstration is not None:
        return FigureData(arrays=arrays, cut=cut)
    return FigureData(trace=reproduction_trace(ep, arrays), cut=cut)


def reproduction_trace(ep: Episode, arrays: dict) -> ReproductionTrace:
    """A reproduction's trace from its recording and its arrays (``demonstration_of``'s):
    the estimates, the commands and the true phases as their messages say them (one that
    does not decode, or lacks a field, is left out)."""
    estimates, commanded, truth_by_seq = [], [], {}
    for m in ep.messages:
        if m.topic not in TRACE_TOPICS:
            continue
        try:
            msg = loads(m.payload)
        except ValueError:
            continue
        try:
            if m.topic == ESTIMATOR_PHASE.channel:
                estimates.append((msg["stamp_ns"] / 1e9, msg["phase"], msg["posterior"], msg.get("seq")))
            elif m.topic == ROBOT_CONTACT.channel:
                truth_by_seq.setdefault(msg["seq"], msg["true_phase"])
            else:
                commanded.append((msg["stamp_ns"] / 1e9, msg["phase"]))
        except (KeyError, TypeError):
            continue
    return ReproductionTrace(t=arrays["t"], forces=arrays["forces"], estimates=sorted(estimates, key=lambda e: e[0]),
                             commanded=sorted(commanded), truth_by_seq=truth_by_seq)


# ------------------------------------------------------------------ for the report


class TopicColumns:
    """What the report reads of one topic's messages (``decoded_messages``), held as a
    64-bit column per field and the few known text values by position: iterated, the
    (log time ns, {field: value}) pairs in the order they were added.  A dict and a tuple
    per message took ~450 bytes, 80 MB for a reproduction of 40 s, on top of its recording
    being read (a sweep's run peaked at 510 MB in its report); a column takes 8 bytes a field."""

    __slots__ = ("names", "log_time", "columns", "text")

    def __init__(self, names):
        self.names = tuple(names)
        self.log_time = array("q")
        self.columns = tuple(array("q") for _ in self.names)
        self.text: dict[int, dict] = {}  # message index -> {field: known text value}

    def append(self, log_time_ns: int, values: dict) -> None:
        self.add(log_time_ns, [values[name] for name in self.names],
                 {k: v for k, v in values.items() if k not in self.names})

    def add(self, log_time_ns: int, row, text: dict | None = None) -> None:
        """One message: its log time, its fields in ``names``' order, its known text values."""
        if text:
            self.text[len(self.log_time)] = text
        self.log_time.append(log_time_ns)
        for column, value in zip(self.columns, row):
            column.append(value)

    def column(self, name: str) -> array:
        """The values of field ``name``, in the order the messages were added."""
        return self.columns[self.names.index(name)]

    def extend(self, other: "TopicColumns") -> None:
        offset = len(self.log_time)
        self.log_time.extend(other.log_time)
        for mine, theirs in zip(self.columns, other.columns):
            mine.extend(theirs)
        self.text.update({offset + i: v for i, v in other.text.items()})

    def __len__(self) -> int:
        return len(self.log_time)

    def __iter__(self):
        names, text = self.names, self.text
        for i, row in enumerate(zip(self.log_time, *self.columns)):
            values = dict(zip(names, row[1:]))
            if i in text:
                values.update(text[i])
            yield row[0], values


_UNSEEN = object()  # a topic decoded_messages has not planned for yet


def decoded_messages(ep) -> tuple[dict, int]:
    """What the report reads of one recorded episode, each message parsed once: per
    topic, the (log time ns, {field: int}) of its messages (a ``TopicColumns``), with the
    known values of the optional text fields in ``REPORT_TEXT`` where a message has one.
    A message that is not JSON, not an object, or lacks one of those fields as an integer
    (garbage from a foreign peer, ``"seq": Infinity``, a wrong schema) is counted, never
    read: one bad message must not cost a run its report."""
    per: dict[str, TopicColumns] = {}
    bad = 0
    plans: dict = {}  # the recording's topic -> (topic, its fields, its text fields) or None: not read
    for msg in ep.messages:
        plan = plans.get(msg.topic, _UNSEEN)
        if plan is _UNSEEN:
            topic = msg.topic.lstrip("/")
            plan = plans[msg.topic] = (topic, REPORT_FIELDS.get(topic, _HEADER), tuple(REPORT_TEXT.get(
                topic, {}).items())) if topic in BY_TOPIC else None
        if plan is None:
            continue
        topic, names, texts = plan
        try:
            d = loads(msg.payload)
            row = [d[k] for k in names]
        except (ValueError, TypeError, KeyError, UnicodeDecodeError):
            bad += 1
            continue
        for v in row:
            if type(v) is not int or not INT_MIN <= v <= INT_MAX:
                break  # the wire's integers are 64-bit; a bigger one would overflow the arrays below
        else:
            columns = per.get(topic)
            if columns is None:
                columns = per[topic] = TopicColumns(names)
            columns.add(msg.log_time_ns, row, {name: d[name] for name, known in texts if d.get(name) in known}
                        if texts else None)
            continue
        bad += 1
    return per, bad


def episode_links(decoded: dict) -> dict:
    """Per topic of one recorded episode: publish -> recorder latency percentiles,
    lost / out-of-order messages judged from the sequence numbers, and the messages
    whose publish stamp is not on the recorder's clock (``off_clock``, not among the
    latencies: ``on_the_clock``)."""
    out = {}
    for topic, items in decoded.items():
        tracker = SequenceTracker(stride=STRIDES.get(topic, 1))
        lat = []
        off = 0
        for log_time, sent_ns, seq in zip(items.log_time, items.column("sent_ns"), items.column("seq")):
            latency = log_time - sent_ns
            if on_the_clock(latency):
                lat.append(latency)
            else:
                off += 1
            tracker.add(seq)
        out[topic] = dict(percentiles(lat), lost=tracker.lost, out_of_order=tracker.out_of_order, off_clock=off)
    return out


def reproduction_phases(decoded: dict, phase_to_truth: dict, dt: float = ESTIMATOR_PERIOD_NS / 1e9) -> dict:
    """Accuracy and transition-time error of the online estimate in one recorded reproduction."""
    contact = decoded.get(ROBOT_CONTACT.topic)
    truth_by_seq = {} if contact is None else dict(zip(contact.column("seq"), contact.column("true_phase")))
    est_by_seq = {d["seq"]: d for _, d in decoded.get(ESTIMATOR_PHASE.topic, ())}
    seqs = sorted(s for s in est_by_seq if s in truth_by_seq)
    if not seqs:
        return {"updates": 0, "accuracy": None, "unconditioned": {"arm_held": 0, "gap": 0}}
    truth = np.array([truth_by_seq[s] for s in seqs])
    est = np.array([est_by_seq[s]["phase"] for s in seqs])
    score = score_segmentation(truth, est, dt=dt, mapping={int(k): int(v) for k, v in phase_to_truth.items()})
    # scored estimates whose step the filter did not condition on (a KRC hold, a missing
    # sample), once per cycle as the accuracy counts them (a replayed copy is not another)
    unconditioned = {"arm_held": 0, "gap": 0}
    for s in seqs:
        why = est_by_seq[s].get("unconditioned")
        if why in unconditioned:
            unconditioned[why] += 1
    return dict(updates=len(seqs), correct=int(round(score.accuracy * len(seqs))), **score.to_dict(),
                unconditioned=unconditioned)


def fri_quality_series(decoded: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(simulated time s, FRI quality, FRI state) of every robot_state in one recorded episode."""
    states = decoded.get(ROBOT_STATE.topic)
    if states is None:
        t, q, st = [], [], []
    else:
        t = [stamp / 1e9 for stamp in states.column("stamp_ns")]
        q, st = states.column("fri_quality"), states.column("fri_state")
    order = np.argsort(t, kind="stable")
    return np.asarray(t)[order], np.asarray(q, dtype=np.int64)[order], np.asarray(st, dtype=np.int64)[order]
