"""A recorded demonstration as the arrays the ETAR learner takes (``load_demonstration``);
``services.cli.etar`` registers it for ``.mcap`` files."""

from __future__ import annotations

import math
import numbers
from pathlib import Path

import numpy as np

from etar.features import force_vector, state_vector
from etar.vocabulary import FEATURES, STATES
from services.recordings.format import RecordingError
from services.recordings.reader import Episode, read_episode
from services.runtime.messages import FT_WRENCH, MessageError, ROBOT_CONTACT, ROBOT_STATE, SAMPLE_RATE_HZ

_DEMONSTRATION_TOPICS = {m.channel: m for m in (ROBOT_STATE, FT_WRENCH, ROBOT_CONTACT)}


def load_demonstration(path, *, state: str = "position", features: str = "force", rate_hz: float = SAMPLE_RATE_HZ,
                       allow_incomplete: bool = False, state_resolution: float = 0.0) -> dict:
    """One recorded demonstration as the ETAR learner takes it.

    Robot cycles (``seq``) that have a robot_state, an ft_wrench and a
    robot_contact are kept, then subsampled to the cycles whose robot_state
    ``stamp_ns`` (simulation time) is a whole multiple of the sample period:
    deterministic, and the same instants whatever cycle the recording began on.

    Returns ``states`` (T, 3) tcp position [m] or (T, 6) position + rotation
    vector of R_0^T R (relative to the first sample; ``etar.features``), its position
    rounded to ``state_resolution`` m if > 0; ``forces``
    (T, 3) the F/T force, or (T, 6) force and torque, in base axes (the sensor
    has the tcp's orientation, so f_base = R f_sensor); ``phases`` (T-1,) the
    true phase of samples 1..T-1 (the label of step t -> t+1 is the phase at
    t+1); ``dt`` [s]; ``t`` (T,) [s] simulation time; ``seq`` (T,) robot
    cycles; ``skipped`` messages that did not decode or repeated a cycle;
    ``gaps`` sample instants between the first and the last with no complete
    cycle; ``complete`` and ``problem`` (``read_episode``'s); ``path``.  An
    incomplete recording raises unless ``allow_incomplete``.
    """
    _sample_period(state, features, rate_hz)  # a wrong argument is said before the file is read
    return demonstration_of(read_episode(path), path, state=state, features=features, rate_hz=rate_hz,
                            allow_incomplete=allow_incomplete, state_resolution=state_resolution)


def demonstration_of(episode: Episode, path, *, state: str = "position", features: str = "force",
                     rate_hz: float = SAMPLE_RATE_HZ, allow_incomplete: bool = False,
                     state_resolution: float = 0.0) -> dict:
    """``load_demonstration``'s arrays from ``episode``, the recording at ``path`` already read
    (by whoever reads it for more than the demonstration)."""
    path = Path(path)
    period_ns = _sample_period(state, features, rate_hz)
    if not episode.complete and not allow_incomplete:
        raise RecordingError(f"{path}: incomplete recording: {episode.problem}; {len(episode.messages)} "
                             "message(s) recovered (load_demonstration(..., allow_incomplete=True) uses them)")

    # of each message only what is used below (a decoded message kept whole cost ~5 kB a robot
    # cycle: 200 MB for a reproduction of 40 s, the report's peak): a state's stamp, episode
    # and, at the sample instants, pose; a wrench's six numbers; a contact's true phase
    by_seq: dict[str, dict[int, object]] = {topic: {} for topic in _DEMONSTRATION_TOPICS}
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
        if mtype is ROBOT_STATE:
            stamp = decoded["stamp_ns"]
            kept = (stamp, decoded.get("episode", 0), decoded["msr_cart_pos"] if stamp % period_ns == 0 else None)
        else:
            kept = decoded["wrench"] if mtype is FT_WRENCH else decoded["true_phase"]
        table[decoded["seq"]] = kept
    for topic, table in by_seq.items():
        if not table:
            found = ", ".join(episode.topics()) or "none"
            raise RecordingError(f"{path}: no {topic} messages that decode "
                                 f"({skipped} skipped; topics in the file: {found})")
    states_by_seq, ft_by_seq, contact_by_seq = (by_seq[t] for t in _DEMONSTRATION_TOPICS)
    # cycles of no episode (episode -1: the arm resting while the sensor is tared) are not demonstration
    states_by_seq = {k: v for k, v in states_by_seq.items() if v[1] != -1} or states_by_seq
    cycles = sorted(states_by_seq.keys() & ft_by_seq.keys() & contact_by_seq.keys())
    if not cycles:
        ranges = "; ".join(f"{t} seq {min(v)}..{max(v)}" for t, v in by_seq.items())
        raise RecordingError(f"{path}: no robot cycle has all of /robot/state, /ft/wrench and /robot/contact "
                             f"({ranges})")
    # the robot cycle, from consecutive cycles: a sample period that is not a
    # multiple of it would pick instants at uneven intervals
    steps = [states_by_seq[b][0] - states_by_seq[a][0] for a, b in zip(cycles, cycles[1:]) if b == a + 1]
    cycle_ns = int(np.median(steps)) if steps else 0
    if cycle_ns <= 0 or period_ns % cycle_ns:
        raise RecordingError(f"{path}: the sample period {period_ns} ns ({rate_hz} Hz) must be a multiple of the "
                             f"robot cycle ({cycle_ns} ns, from {len(steps)} consecutive cycles)")
    chosen = [s for s in cycles if states_by_seq[s][0] % period_ns == 0]
    if len(chosen) < 2:
        raise RecordingError(f"{path}: {len(chosen)} sample(s) at {rate_hz} Hz from {len(cycles)} complete "
                             "robot cycles; a demonstration needs at least 2")

    stamp_ns = np.array([states_by_seq[s][0] for s in chosen], dtype=np.int64)
    if np.any(np.diff(stamp_ns) <= 0):
        raise RecordingError(f"{path}: robot_state stamp_ns does not increase with seq")
    cart = np.array([states_by_seq[s][2] for s in chosen], dtype=np.float64).reshape(-1, 3, 4)
    R = cart[:, :, :3]
    wrench = np.array([ft_by_seq[s] for s in chosen], dtype=np.float64)
    true_phase = np.array([contact_by_seq[s] for s in chosen], dtype=np.int64)

    # the same functions as the online estimator, so learner and estimator see the same numbers
    R0 = R[0]
    states = np.array([state_vector(c, state, R0, state_resolution) for c in cart.reshape(-1, 12)])
    forces = np.array([force_vector(w, c, features) for w, c in zip(wrench, cart.reshape(-1, 12))])

    gaps = int((stamp_ns[-1] - stamp_ns[0]) // period_ns + 1 - len(chosen))
    return dict(states=states, forces=forces, phases=true_phase[1:], dt=period_ns * 1e-9, t=stamp_ns * 1e-9,
                seq=np.array(chosen, dtype=np.int64), skipped=skipped, gaps=gaps, complete=episode.complete,
                problem=episode.problem, path=str(path))


def _sample_period(state: str, features: str, rate_hz: float) -> int:
    """The sample period in ns, once ``state``, ``features`` and ``rate_hz`` are known to be valid."""
    if state not in STATES:
        raise RecordingError(f"state must be one of {sorted(STATES)}, got {state!r}")
    if features not in FEATURES:
        raise RecordingError(f"features must be one of {sorted(FEATURES)}, got {features!r}")
    return _sample_period_ns(rate_hz)


def _sample_period_ns(rate_hz: float) -> int:
    if isinstance(rate_hz, bool) or not isinstance(rate_hz, numbers.Real) or not (
            math.isfinite(rate_hz) and rate_hz > 0):
        raise RecordingError(f"rate_hz must be a positive number, got {rate_hz!r}")
    period = round(1e9 / rate_hz)
    if abs(period - 1e9 / rate_hz) > 1e-3:
        raise RecordingError(f"rate_hz {rate_hz} does not give a whole number of nanoseconds per sample")
    return period


