"""What one recording holds (``etar-bench info FILE.mcap``): the file, its size, the MCAP
profile and library, whether the writer finished it (``read_episode``: complete, or what
a truncated file lost), the run and the episode (the ``etar`` metadata record), the
scenario attached (name, seed, world, clock), the code version when the recording carries
one, the simulated duration, per topic the schema, message count, rate and gaps, and the
episode's result (the robot's episode summary, with the run's report.json verdict when the
file lies in a run's ``recordings/``).

Times: a recording's log times are the recorder's receive times on the host's
CLOCK_MONOTONIC (``services.recordings.format``), so the simulated duration comes from
the messages' ``stamp_ns``: the span of the robot-cycle topics' stamps plus one FRI
cycle (N cycles cover N ms).  A topic's ``rate_hz`` is its messages over that duration,
``nominal_hz`` what its period (``services.runtime.messages``) says.  Gaps, for the
topics with a period: ``missing`` sequence numbers between the first and the last
(seq counts FRI cycles, so a topic every tenth cycle advances by ten), ``duplicates``,
and ``gaps`` the intervals between consecutive stamps longer than 1.5 periods, the
``largest_gap_s`` with the cycle it ended at.
"""

from __future__ import annotations

import json
from pathlib import Path

from mcap.exceptions import McapError
from mcap.stream_reader import StreamReader

from robot_sim.cycle import FRI_CYCLE_NS
from services.recordings.reader import Episode, read_episode
from services.results.folder import strict_json
from services.results.info.common import InfoError, code_line, in_run, scenario_line, scenario_summary, size_text
from services.runtime.messages import BY_TOPIC, EPISODE_SUMMARY, loads

# the metadata record's keys that say which code wrote a recording (services.recordings.writer)
CODE_KEYS = ("code_version", "code_commit", "code_dirty")

# metadata keys the writer always puts in the etar record, shown as the run and episode or not at all
_EPISODE_KEYS = ("run_id", "episode_kind", "episode_index", "log_time", "publish_time")

GAP_FACTOR = 1.5  # an interval between consecutive stamps longer than this many periods is a gap


def describe_recording(path) -> dict:
    """One recording as plain data (module docstring); RecordingError if it does not read."""
    path = Path(path)
    if path.is_dir():
        raise InfoError(f"{path}: a folder, not a recording")
    ep = read_episode(path)
    metadata = dict(ep.metadata)
    index = metadata.get("episode_index")
    topics = _topics(ep)
    sim = _simulated_span(topics)
    for t in topics.values():
        t["rate_hz"] = t["messages"] / sim["seconds"] if sim and sim["seconds"] > 0 else None
        del t["_stamps"]
    logs = [m.log_time_ns for m in ep.messages]
    return strict_json({
        "kind": "recording",
        "file": str(path),
        "size_bytes": path.stat().st_size,
        "mcap": {"profile": _profile(path), "library": ep.library, "chunks": ep.chunks},
        "complete": ep.complete,
        "problem": ep.problem,
        "run_id": metadata.get("run_id"),
        "episode": {"kind": metadata.get("episode_kind"),
                    "index": int(index) if index is not None and index.lstrip("-").isdigit() else index},
        "scenario": scenario_summary(ep.scenario_text, metadata.get("scenario")),
        "code": _code(metadata),
        # the rest of the record (start, model, part, ...); the scenario's name is in "scenario"
        "metadata": {k: v for k, v in metadata.items() if k not in _EPISODE_KEYS and k not in CODE_KEYS
                     and k != "scenario"},
        "simulated": sim,
        "log_time": {"first_ns": min(logs), "last_ns": max(logs), "seconds": (max(logs) - min(logs)) / 1e9,
                     "clock": metadata.get("log_time", "")} if logs else None,
        "messages": len(ep.messages),
        "topics": [dict(topic=name, **t) for name, t in sorted(topics.items())],
        "result": _result(ep, path, metadata.get("episode_kind")),
    })


def _profile(path: Path) -> str | None:
    """The MCAP header's profile (the reader keeps only the library)."""
    try:
        with open(path, "rb") as f:
            for record in StreamReader(f, skip_magic=False).records:
                return getattr(record, "profile", None)
    except (McapError, OSError, ValueError, EOFError):
        return None
    return None


def _topics(ep: Episode) -> dict:
    """Per topic: schema, count, seq range, undecodable payloads, and the gaps of a periodic one."""
    out: dict[str, dict] = {}
    for name, ch in ep.channels.items():
        out[name] = _topic_entry(ch.schema_name)
    seqs: dict[str, list] = {}
    for m in ep.messages:
        t = out.setdefault(m.topic, _topic_entry(""))
        t["messages"] += 1
        try:
            d = loads(m.payload)
        except (ValueError, TypeError):
            t["undecodable"] += 1
            continue
        if not isinstance(d, dict):
            t["undecodable"] += 1
            continue
        seq, stamp = d.get("seq"), d.get("stamp_ns")
        if stamp is None and isinstance(d.get("timestamp"), dict):  # a visual topic: Foxglove's time
            ts = d["timestamp"]
            stamp = ts.get("sec", 0) * 1_000_000_000 + ts.get("nsec", 0)
        if _is_int(seq):
            seqs.setdefault(m.topic, []).append(seq)
        if _is_int(stamp):
            t["_stamps"].append((stamp, seq if _is_int(seq) else None))
    for name, t in out.items():
        mtype = BY_TOPIC.get(name.lstrip("/"))
        period = mtype.period_ns if mtype is not None else None
        s = seqs.get(name, [])
        t["seq_first"], t["seq_last"] = (min(s), max(s)) if s else (None, None)
        t["period_ns"] = period
        t["nominal_hz"] = 1e9 / period if period else None
        t["gaps"] = _gaps(s, t["_stamps"], period) if period else None
    return out


def _topic_entry(schema: str) -> dict:
    return {"schema": schema, "messages": 0, "undecodable": 0, "_stamps": []}


def _gaps(seqs: list, stamps: list, period_ns: int) -> dict:
    stride = max(1, period_ns // FRI_CYCLE_NS)
    unique = sorted(set(seqs))
    expected = (unique[-1] - unique[0]) // stride + 1 if unique else 0
    times = sorted(set(stamps), key=lambda x: x[0])
    largest, at_seq, count = 0, None, 0
    for (t0, _), (t1, seq) in zip(times, times[1:]):
        dt = t1 - t0
        if dt > GAP_FACTOR * period_ns:
            count += 1
        if dt > largest:
            largest, at_seq = dt, seq
    return {"missing": max(0, expected - len(unique)), "duplicates": len(seqs) - len(unique), "gaps": count,
            "largest_gap_s": largest / 1e9 if len(times) > 1 else None,
            "largest_gap_periods": largest / period_ns if len(times) > 1 else None,
            "largest_gap_ends_at_seq": at_seq}


def _simulated_span(topics: dict) -> dict | None:
    """The episode's simulated time: the robot-cycle topics' stamps (others as a fallback)."""
    periodic = [s for t in topics.values() if t["period_ns"] for s, _ in t["_stamps"]]
    if periodic:
        first, last = min(periodic), max(periodic)
        return {"first_ns": first, "last_ns": last, "seconds": (last - first + FRI_CYCLE_NS) / 1e9,
                "basis": "robot-cycle stamps, plus one FRI cycle"}
    stamps = [s for t in topics.values() for s, _ in t["_stamps"] if s > 0]
    if not stamps:
        return None
    return {"first_ns": min(stamps), "last_ns": max(stamps), "seconds": (max(stamps) - min(stamps)) / 1e9,
            "basis": "message stamps"}


def _code(metadata: dict) -> dict | None:
    """The code that wrote a recording, as its writer put it in the metadata record
    (``services.runtime.provenance.code``); None for a file that does not say."""
    if "code_version" not in metadata:
        return None
    commit = metadata.get("code_commit")
    return {"version": metadata["code_version"], "commit": None if commit in (None, "None") else commit,
            "dirty": {"True": True, "False": False}.get(metadata.get("code_dirty"))}


def _result(ep: Episode, path: Path, kind: str | None) -> dict | None:
    """The robot's episode summary (the last one in the file), and the run report's verdict."""
    summaries = [m for m in ep.messages if m.topic == "/" + EPISODE_SUMMARY.topic]
    out = None
    for m in reversed(summaries):
        try:
            d = loads(m.payload)
        except (ValueError, TypeError):
            continue
        if isinstance(d, dict):
            out = {k: d.get(k) for k in ("reason", "sim_seconds", "wall_seconds", "first_seq", "last_seq",
                                         "peak_contact_force", "safety", "goal_reached_at_s")}
            if kind != "demonstration":
                at = d.get("goal_reached_at_s")
                out["goal_reached"] = (at >= 0) if isinstance(at, (int, float)) else d.get("reason") == "goal_reached"
            out["source"] = "episode summary"
            break
    verdict = _report_entry(path)
    if verdict is not None:
        out = dict(out or {"reason": verdict.get("reason"), "sim_seconds": verdict.get("sim_seconds")})
        for k in ("success", "reached_goal", "bounded_force"):
            if k in verdict:
                out[k] = verdict[k]
        acc = (verdict.get("phases") or {}).get("accuracy")
        if acc is not None:
            out["phase_accuracy"] = acc
        out["source"] = (out.get("source", "") + " + report.json").lstrip(" +")
    return out


def _report_entry(path: Path) -> dict | None:
    """The entry of the run's report.json for a recording in RUN/recordings/, if any."""
    run_dir = path.resolve().parent.parent
    try:
        report = json.loads((run_dir / "report.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(report, dict):
        return None
    for entry in ((report.get("demonstrations") or []) + (report.get("reproductions") or [])
                  + (report.get("served") or [])):
        if not isinstance(entry, dict) or not entry.get("path"):
            continue
        paths = [entry["path"], *(entry.get("recording_parts") or [])]
        if any(in_run(run_dir, p) == path.resolve() for p in paths):
            return entry
    return None


def recording_text(d: dict) -> str:
    """``describe_recording``'s data for people."""
    state = "complete" if d["complete"] else f"INCOMPLETE: {d['problem']}"
    ep = d["episode"]
    sc = d["scenario"]
    lines = [f"recording  {d['file']}",
             f"  file      {size_text(d['size_bytes'])}, {state}",
             f"  MCAP      profile {d['mcap']['profile']!r}, library {d['mcap']['library']!r}, "
             f"{d['mcap']['chunks']} chunk(s)",
             f"  run       {d['run_id'] or '?'}, {ep['kind'] or '?'} {ep['index'] if ep['index'] is not None else '?'}",
             f"  scenario  {scenario_line(sc)}" + ("" if sc.get("attached") else " (no scenario attached)"),
             f"  code      {code_line(d['code'])}"]
    sim = d["simulated"]
    log = d["log_time"]
    if sim:
        duration = (f"{sim['seconds']:.3f} s simulated (stamps {sim['first_ns'] / 1e9:.3f} .. "
                    f"{sim['last_ns'] / 1e9:.3f} s)")
    else:
        duration = "no simulated time (no stamped messages)"
    if log:
        duration += f"; received over {log['seconds']:.3f} s of the host's clock"
    lines.append(f"  duration  {duration}")
    lines.append(f"  result    {_result_line(d['result'])}")
    for k, v in d["metadata"].items():
        lines.append(f"  {k:<9} {v}")
    lines += ["", f"  {d['messages']} messages on {len(d['topics'])} topics:",
              "  topic              schema                     messages  rate [Hz]  nominal  missing seq  "
              "gaps > 1.5 T  largest gap"]
    for t in d["topics"]:
        g = t["gaps"]
        rate = f"{t['rate_hz']:9.1f}" if t["rate_hz"] is not None else f"{'-':>9}"
        if t["nominal_hz"]:
            nominal = f"{t['nominal_hz']:7g}"
        else:  # a defined message without a period comes on events; a visual topic at the recorder's rate
            nominal = f"{'events' if t['topic'].lstrip('/') in BY_TOPIC else '-':>7}"
        if g is None:
            gaps = f"{'-':>11}  {'-':>12}  -"
        else:
            largest = "-" if g["largest_gap_s"] is None else \
                f"{g['largest_gap_s'] * 1e3:g} ms" + (f" (to seq {g['largest_gap_ends_at_seq']})"
                                                      if g["gaps"] else "")
            gaps = f"{g['missing']:>11}  {g['gaps']:>12}  {largest}"
            if g["duplicates"]:
                gaps += f", {g['duplicates']} duplicate seq"
        bad = f"  ({t['undecodable']} undecodable)" if t["undecodable"] else ""
        lines.append(f"  {t['topic']:<18} {t['schema']:<26} {t['messages']:>8}  {rate}  {nominal}  {gaps}{bad}")
    return "\n".join(lines) + "\n"


def _result_line(r: dict | None) -> str:
    if not r:
        return "none recorded (no episode summary: the episode did not end in this file)"
    parts = [str(r.get("reason") or "?")]
    if r.get("sim_seconds") is not None:
        parts[0] += f" after {r['sim_seconds']:.3f} s simulated"
    if "goal_reached" in r:
        at = r.get("goal_reached_at_s")
        parts.append(f"goal reached at {at:.3f} s" if r["goal_reached"] and isinstance(at, (int, float)) and at >= 0
                     else "goal reached" if r["goal_reached"] else "goal not reached")
    if r.get("peak_contact_force") is not None:
        parts.append(f"peak contact {r['peak_contact_force']:.1f} N")
    if r.get("success") is not None:
        parts.append("success" if r["success"] else "FAILED")
    if r.get("phase_accuracy") is not None:
        parts.append(f"phase accuracy {r['phase_accuracy']:.4f}")
    return "; ".join(parts) + f"  [{r.get('source')}]"


def _is_int(x) -> bool:
    return type(x) is int
