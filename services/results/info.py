"""What a recording or a run folder holds, at a glance (``etar-bench info PATH [--json]``).

``describe(path)`` returns plain data (strict JSON: no NaN, no numpy) and
``info_text(d)`` the same for people.

A recording (``.mcap``): the file, its size, the MCAP profile and library, whether the
writer finished it (``read_episode``: complete, or what a truncated file lost), the run
and the episode (the ``etar`` metadata record), the scenario attached (name, seed, world,
clock), the code version when the recording carries one, the simulated duration, per
topic the schema, message count, rate and gaps, and the episode's result (the robot's
episode summary, with the run's report.json verdict when the file lies in a run's
``recordings/``).

Times: a recording's log times are the recorder's receive times on the host's
CLOCK_MONOTONIC (``services.recordings.format``), so the simulated duration comes from
the messages' ``stamp_ns``: the span of the robot-cycle topics' stamps plus one FRI
cycle (N cycles cover N ms).  A topic's ``rate_hz`` is its messages over that duration,
``nominal_hz`` what its period (``services.runtime.messages``) says.  Gaps, for the
topics with a period: ``missing`` sequence numbers between the first and the last
(seq counts FRI cycles, so a topic every tenth cycle advances by ten), ``duplicates``,
and ``gaps`` the intervals between consecutive stamps longer than 1.5 periods, the
``largest_gap_s`` with the cycle it ended at.

A run folder: the scenario (and its seed), run id, transport and clock, the result
(report.json's ``summary`` and ``error``), the model (phases, how they were chosen),
every episode (kind, index, result, simulated duration, messages from the MCAP summary
without reading the data) with totals, and report.json's ``provenance`` when it has one.

Errors: a path that does not exist, a folder that holds no run, an unreadable
report.json raise ``InfoError``; a file that is not MCAP or a damaged recording raise
``RecordingError`` (``read_episode``'s); both are ValueErrors whose one-line message
names the file.
"""

from __future__ import annotations

import json
from pathlib import Path

import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from robot_sim.cycle import FRI_CYCLE_NS
from services.recordings.format import METADATA_NAME, SCENARIO_ATTACHMENT, RecordingError
from services.recordings.reader import Episode, read_episode
from services.results.folder import SCENARIO_FILE, read_report, strict_json
from services.runtime.provenance import describe_code
from services.runtime.messages import BY_TOPIC, EPISODE_SUMMARY, loads

# the metadata record's keys that say which code wrote a recording (services.recordings.writer)
CODE_KEYS = ("code_version", "code_commit", "code_dirty")
# metadata keys the writer always puts in the etar record, shown as the run and episode or not at all
_EPISODE_KEYS = ("run_id", "episode_kind", "episode_index", "log_time", "publish_time")
GAP_FACTOR = 1.5  # an interval between consecutive stamps longer than this many periods is a gap


class InfoError(ValueError):
    """A path ``describe`` cannot describe, naming it and why."""


def describe(path) -> dict:
    """A recording (a file) or a run folder (a folder, or its report.json) as plain data."""
    p = Path(path)
    if not p.exists():
        raise InfoError(f"{p}: no such file or folder")
    if p.is_dir():
        return describe_run(p)
    if p.name == "report.json":
        return describe_run(p.parent)
    return describe_recording(p)


# ---------------------------------------------------------------------------
# one recording
# ---------------------------------------------------------------------------


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
        "scenario": _scenario(ep.scenario_text, metadata.get("scenario")),
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


def _scenario(text: str | None, name: str | None) -> dict:
    """Name, seed, world and clock of a scenario's YAML (the attachment, or the run's file)."""
    if text is None:
        return {"attached": False, "name": name, "seed": None}
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        return {"attached": True, "name": name, "seed": None, "problem": f"does not parse: {exc}".splitlines()[0]}
    if not isinstance(data, dict):
        return {"attached": True, "name": name, "seed": None, "problem": "not a mapping"}
    return {"attached": True, "name": data.get("name", name), "seed": data.get("seed"),
            "world": data.get("world"), "clock": data.get("clock")}


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
        if any(_in_run(run_dir, p) == path.resolve() for p in paths):
            return entry
    return None


# ---------------------------------------------------------------------------
# a run folder
# ---------------------------------------------------------------------------


def describe_run(path) -> dict:
    """A run folder as plain data (module docstring): report.json and the MCAP summaries of
    its recordings, without reading their messages."""
    run_dir = Path(path)
    report_path = run_dir / "report.json"
    recordings = run_dir / "recordings"
    if not run_dir.is_dir():
        raise InfoError(f"{run_dir}: not a folder")
    if not report_path.exists() and not recordings.is_dir():
        raise InfoError(f"{run_dir}: not a run folder (no report.json, no recordings/)")
    report = read_report(run_dir, required=False)

    episodes, listed = [], set()
    for kind, key in (("demonstration", "demonstrations"), ("reproduction", "reproductions"), ("served", "served")):
        for i, entry in enumerate(report.get(key) or []):
            if not isinstance(entry, dict):
                continue
            files = [_in_run(run_dir, p) for p in [entry.get("path"), *(entry.get("recording_parts") or [])] if p]
            listed.update(files)
            stats = [_file_stats(f) for f in files]
            episodes.append(_episode(kind, entry.get("index", i), entry, files, stats, run_dir))
    for f in sorted(recordings.glob("*.mcap")) if recordings.is_dir() else ():
        if f.resolve() in listed:
            continue
        st = _file_stats(f.resolve())  # a recording the report does not name (a run cut short)
        episodes.append(_episode(st.get("episode_kind") or "?", st.get("episode_index"), {}, [f.resolve()], [st],
                                 run_dir))

    environment = report.get("environment") or {}
    scenario = _run_scenario(run_dir, report, episodes)
    totals = {"episodes": len(episodes),
              "messages": sum(e["messages"] or 0 for e in episodes),
              "size_bytes": sum(e["size_bytes"] or 0 for e in episodes),
              "sim_seconds": sum(e["sim_seconds"] or 0 for e in episodes),
              "incomplete": sum(not e["complete"] for e in episodes)}
    return strict_json({
        "kind": "run",
        "path": str(run_dir),
        "report": report_path.exists(),
        "scenario": scenario,
        "run_id": report.get("run_id"),
        "transport": report.get("transport"),
        "clock": environment.get("clock") or scenario.get("clock"),
        "error": report.get("error"),
        "wall_seconds": report.get("wall_seconds"),
        "summary": report.get("summary"),
        "provenance": report.get("provenance"),
        "model": _model(run_dir, report),
        "episodes": episodes,
        "totals": totals,
    })


def run_scenario(run_dir) -> dict:
    """A run folder's scenario: name, seed, world, clock, from the scenario file the run wrote
    (or the first recording's attachment); ``describe_run`` and ``diff_runs`` read it."""
    run_dir = Path(run_dir)
    try:
        report = json.loads((run_dir / "report.json").read_text())
    except (OSError, ValueError):
        report = {}
    return _run_scenario(run_dir, report if isinstance(report, dict) else {}, [])


def _run_scenario(run_dir: Path, report: dict, episodes: list) -> dict:
    text = None
    try:
        text = (run_dir / SCENARIO_FILE).read_text()
        origin = SCENARIO_FILE
    except OSError:
        files = [Path(f) for e in episodes for f in e["files"]] or sorted((run_dir / "recordings").glob("*.mcap"))
        for f in files:
            text = _attached_scenario(f if f.is_absolute() else run_dir / f)
            if text is not None:
                origin = f"{SCENARIO_ATTACHMENT} of {Path(f).name}"
                break
    out = _scenario(text, report.get("scenario"))
    out.pop("attached")
    out["from"] = origin if text is not None else None
    out["source"] = report.get("source")
    return out


def _attached_scenario(path: Path) -> str | None:
    try:
        with open(path, "rb") as f:
            for att in make_reader(f).iter_attachments():
                if att.name == SCENARIO_ATTACHMENT:
                    return att.data.decode("utf-8", errors="replace")
    except (McapError, OSError, ValueError, EOFError, AttributeError):
        return None
    return None


def _file_stats(path: Path) -> dict:
    """A recording's size, message count and episode, from its MCAP summary (the footer's
    statistics and metadata index: no message is read); a file without one (truncated) is
    read through; one that does not read has its ``problem``."""
    out = {"path": path, "size_bytes": None, "messages": None, "complete": False, "problem": None,
           "episode_kind": None, "episode_index": None}
    try:
        out["size_bytes"] = path.stat().st_size
    except OSError as exc:
        out["problem"] = f"{path}: {exc.strerror or exc}"
        return out
    metadata = None
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is not None and summary.statistics is not None:
                out["messages"] = summary.statistics.message_count
                out["complete"] = True
                metadata = next((m.metadata for m in reader.iter_metadata() if m.name == METADATA_NAME), {})
    except (McapError, OSError, ValueError, EOFError, AttributeError, RuntimeError):
        pass
    if metadata is None:
        try:
            ep = read_episode(path)
        except RecordingError as exc:
            out["problem"] = str(exc)
            return out
        out.update(messages=len(ep.messages), complete=ep.complete, problem=ep.problem)
        metadata = ep.metadata
    index = metadata.get("episode_index")
    out["episode_kind"] = metadata.get("episode_kind")
    out["episode_index"] = int(index) if index is not None and index.lstrip("-").isdigit() else index
    return out


def _episode(kind: str, index, entry: dict, files: list, stats: list, run_dir: Path) -> dict:
    problems = [s["problem"] for s in stats if s["problem"]]
    return {"kind": kind, "index": index,
            "files": [_relative(run_dir, f) for f in files],
            "reason": entry.get("reason"),
            "success": entry.get("success"),
            "phase_accuracy": (entry.get("phases") or {}).get("accuracy"),
            "peak_contact_force": entry.get("peak_contact_force"),
            "sim_seconds": entry.get("sim_seconds"),
            "wall_seconds": entry.get("wall_seconds"),
            "messages": sum(s["messages"] for s in stats) if stats and all(s["messages"] is not None for s in stats)
            else None,
            "size_bytes": sum(s["size_bytes"] or 0 for s in stats),
            "complete": bool(stats) and all(s["complete"] for s in stats),
            "problem": "; ".join(problems) or None}


def _model(run_dir: Path, report: dict) -> dict | None:
    """The run's model: its file, number of phases, transition model, how the phases were chosen."""
    learning = report.get("learning") or {}
    selection = learning.get("selection") or {}
    files = {name: m.get("path") for name, m in (learning.get("models") or {}).items() if isinstance(m, dict)}
    if not files and learning.get("model"):
        files = {None: learning["model"]}
    if not files and (run_dir / "model.json").exists():
        files = {None: "model.json"}
    if not files and not selection:
        return None
    models = []
    for name, rel in files.items():
        entry = {"name": name, "file": rel, "phases": None, "transitions": None}
        try:
            m = json.loads(_in_run(run_dir, rel).read_text())
            entry.update(phases=m.get("n_phases"), transitions=m.get("transitions"),
                         state=(m.get("metadata") or {}).get("state"),
                         features=(m.get("metadata") or {}).get("features"))
        except (OSError, ValueError, AttributeError) as exc:
            entry["problem"] = f"{rel}: {exc.strerror if isinstance(exc, OSError) else 'not a model file'}"
        models.append(entry)
    return {"phases_chosen": selection.get("best", (report.get("summary") or {}).get("phases_chosen")),
            "criterion": selection.get("criterion"), "scores": selection.get("scores") or None,
            "learn_seconds": learning.get("seconds"), "models": models}


def _in_run(run_dir: Path, p) -> Path:
    p = Path(p)
    return (p if p.is_absolute() else run_dir / p).resolve()


def _relative(run_dir: Path, p: Path) -> str:
    try:
        return str(Path(p).relative_to(run_dir.resolve()))
    except ValueError:
        return str(p)


# ---------------------------------------------------------------------------
# text
# ---------------------------------------------------------------------------


def info_text(d: dict) -> str:
    """``describe``'s data for people."""
    return _run_text(d) if d.get("kind") == "run" else _recording_text(d)


def _recording_text(d: dict) -> str:
    state = "complete" if d["complete"] else f"INCOMPLETE: {d['problem']}"
    ep = d["episode"]
    sc = d["scenario"]
    lines = [f"recording  {d['file']}",
             f"  file      {_size(d['size_bytes'])}, {state}",
             f"  MCAP      profile {d['mcap']['profile']!r}, library {d['mcap']['library']!r}, "
             f"{d['mcap']['chunks']} chunk(s)",
             f"  run       {d['run_id'] or '?'}, {ep['kind'] or '?'} {ep['index'] if ep['index'] is not None else '?'}",
             f"  scenario  {_scenario_line(sc)}" + ("" if sc.get("attached") else " (no scenario attached)"),
             f"  code      {_code_line(d['code'])}"]
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


def _run_text(d: dict) -> str:
    sc = d["scenario"]
    lines = [f"run        {d['path']}" + ("" if d["report"] else "  (no report.json: the run did not finish)"),
             f"  scenario  {_scenario_line(sc)}" + (f", from {sc['source']}" if sc.get("source") else ""),
             f"  run id    {d['run_id'] or '?'}",
             f"  transport {d['transport'] or '?'}, clock {d['clock'] or '?'}"
             + (f", {d['wall_seconds']:.1f} s wall" if isinstance(d["wall_seconds"], (int, float)) else "")]
    prov = d.get("provenance") or {}
    if prov:
        code = _code_line(prov)
        lines.append(f"  code      {code}")
        for k in ("date", "command"):
            if prov.get(k):
                lines.append(f"  {k:<9} {prov[k]}")
    s = d.get("summary") or {}
    if d["report"]:
        result = "ERROR: " + str(d["error"]) if d["error"] else "ok"
        if s:
            acc = s.get("online_phase_accuracy")
            err = s.get("mean_transition_error_s")
            result += (f"; {s.get('phases_chosen')} phases; {s.get('successes')} of {s.get('reproductions')} "
                       f"reproductions succeeded; online phase accuracy {_num(acc, '.4f')}; mean transition error "
                       f"{_num(err, '.3f')} s")
        lines.append(f"  result    {result}")
    m = d.get("model")
    if m:
        chosen = f"{m['phases_chosen']} phases" + (f" ({m['criterion']})" if m.get("criterion") else "")
        files = ", ".join(f"{x['name'] + ': ' if x['name'] else ''}{x['file']} "
                          f"({x['phases']} phases, {x['transitions']} transitions)" if not x.get("problem")
                          else x["problem"] for x in m["models"]) or "no model file"
        lines.append(f"  model     {chosen}; {files}")
    else:
        lines.append("  model     none")
    lines += ["", "  episode            result              success  phase acc  sim [s]  wall [s]  messages"
              "       size  file"]
    for e in d["episodes"]:
        success = "-" if e["success"] is None else ("yes" if e["success"] else "NO")
        file = ", ".join(e["files"]) + ("" if e["complete"] else f"  INCOMPLETE: {e['problem']}")
        lines.append(f"  {e['kind']:<14} {str(e['index']):>3} {str(e['reason'] or '-'):<19} {success:>7}  "
                     f"{_num(e['phase_accuracy'], '.4f'):>9}  {_num(e['sim_seconds'], '.3f'):>7}  "
                     f"{_num(e['wall_seconds'], '.2f'):>8}  {_num(e['messages'], 'd'):>8}  "
                     f"{_size(e['size_bytes']):>9}  {file}")
    t = d["totals"]
    lines.append(f"  {'total':<18} {t['episodes']} episode(s){'':<17}{_num(t['sim_seconds'], '.3f'):>7}  "
                 f"{'':>8}  {t['messages']:>8}  {_size(t['size_bytes']):>9}"
                 + (f"  {t['incomplete']} incomplete" if t["incomplete"] else ""))
    return "\n".join(lines) + "\n"


def _scenario_line(sc: dict) -> str:
    parts = [str(sc.get("name") or "?"), f"seed {sc['seed']}" if sc.get("seed") is not None else "seed ?"]
    extra = ", ".join(f"{k} {sc[k]}" for k in ("world", "clock") if sc.get(k))
    return ", ".join(parts) + (f" ({extra})" if extra else "") + (f" [{sc['problem']}]" if sc.get("problem") else "")


def _code_line(code: dict | None) -> str:
    return describe_code(code) if code else "not recorded"


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


def _num(x, spec: str) -> str:
    return "-" if x is None or isinstance(x, bool) else format(x, spec)


def _size(n: int | None) -> str:
    if n is None:
        return "-"
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


def _is_int(x) -> bool:
    return type(x) is int
