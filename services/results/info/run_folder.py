"""What a run folder holds (``etar-bench info RUN_DIR``): the scenario (and its seed), run
id, transport and clock, the result (report.json's ``summary`` and ``error``), the model
(phases, how they were chosen), every episode (kind, index, result, simulated duration,
messages from the MCAP summary without reading the data) with totals, and report.json's
``provenance`` when it has one."""

from __future__ import annotations

import json
from pathlib import Path

from mcap.exceptions import McapError
from mcap.reader import make_reader

from services.recordings.format import METADATA_NAME, SCENARIO_ATTACHMENT, RecordingError
from services.recordings.reader import read_episode
from services.results.folder import SCENARIO_FILE, read_report, report_episodes, strict_json
from services.results.info.common import InfoError, code_line, in_run, scenario_line, scenario_summary, size_text


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
        for i, entry in enumerate(report_episodes(report, key, report_path)):
            if not isinstance(entry, dict):
                continue
            files = [in_run(run_dir, p) for p in [entry.get("path"), *(entry.get("recording_parts") or [])] if p]
            listed.update(files)
            # no recordings/ at all: the run kept none by choice (a sweep's --record summary), none is lost
            stats = [_file_stats(f) for f in files] if recordings.is_dir() else [_NOT_KEPT] if files else []
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
              "incomplete": sum(e["complete"] is False for e in episodes)}
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
    out = scenario_summary(text, report.get("scenario"))
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


# an episode's recording when the run kept none: neither complete nor lost
_NOT_KEPT = {"size_bytes": None, "messages": None, "complete": None, "problem": "not kept: the run has no recordings/"}


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
            # the parts before the last are cut by design (a recorder restarted mid-episode, the
            # report's recording_gaps): the episode is whole when every part reads and the last is finished
            "complete": None if stats == [_NOT_KEPT] else
            bool(stats) and stats[-1]["complete"] and all(s["messages"] is not None for s in stats),
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
            m = json.loads(in_run(run_dir, rel).read_text())
            entry.update(phases=m.get("n_phases"), transitions=m.get("transitions"),
                         state=(m.get("metadata") or {}).get("state"),
                         features=(m.get("metadata") or {}).get("features"))
        except (OSError, ValueError, AttributeError, RecursionError) as exc:  # nested past the parser's bound
            entry["problem"] = f"{rel}: {exc.strerror if isinstance(exc, OSError) else 'not a model file'}"
        models.append(entry)
    return {"phases_chosen": selection.get("best", (report.get("summary") or {}).get("phases_chosen")),
            "criterion": selection.get("criterion"), "scores": selection.get("scores") or None,
            "learn_seconds": learning.get("seconds"), "models": models}


def _relative(run_dir: Path, p: Path) -> str:
    try:
        return str(Path(p).relative_to(run_dir.resolve()))
    except ValueError:
        return str(p)


def run_text(d: dict) -> str:
    """``describe_run``'s data for people."""
    sc = d["scenario"]
    lines = [f"run        {d['path']}" + ("" if d["report"] else "  (no report.json: the run did not finish)"),
             f"  scenario  {scenario_line(sc)}" + (f", from {sc['source']}" if sc.get("source") else ""),
             f"  run id    {d['run_id'] or '?'}",
             f"  transport {d['transport'] or '?'}, clock {d['clock'] or '?'}"
             + (f", {d['wall_seconds']:.1f} s wall" if isinstance(d["wall_seconds"], (int, float)) else "")]
    prov = d.get("provenance") or {}
    if prov:
        code = code_line(prov)
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
            phases = "no phases chosen" if s.get("phases_chosen") is None else f"{s['phases_chosen']} phases"
            result += (f"; {phases}; {s.get('successes')} of {s.get('reproductions')} "
                       f"reproductions succeeded; online phase accuracy {_num(acc, '.4f')}; mean transition error "
                       f"{_num(err, '.3f')} s")
        lines.append(f"  result    {result}")
    m = d.get("model")
    if m:
        chosen = ("no phases chosen" if m["phases_chosen"] is None else f"{m['phases_chosen']} phases") \
            + (f" ({m['criterion']})" if m.get("criterion") else "")
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
        file = ", ".join(e["files"]) + ("" if e["complete"] else f"  ({e['problem']})" if e["complete"] is None
                                        else f"  INCOMPLETE: {e['problem']}")
        lines.append(f"  {e['kind']:<14} {str(e['index']):>3} {str(e['reason'] or '-'):<19} {success:>7}  "
                     f"{_num(e['phase_accuracy'], '.4f'):>9}  {_num(e['sim_seconds'], '.3f'):>7}  "
                     f"{_num(e['wall_seconds'], '.2f'):>8}  {_num(e['messages'], 'd'):>8}  "
                     f"{size_text(e['size_bytes']):>9}  {file}")
    t = d["totals"]
    lines.append(f"  {'total':<18} {t['episodes']} episode(s){'':<17}{_num(t['sim_seconds'], '.3f'):>7}  "
                 f"{'':>8}  {t['messages']:>8}  {size_text(t['size_bytes']):>9}"
                 + (f"  {t['incomplete']} incomplete" if t["incomplete"] else ""))
    return "\n".join(lines) + "\n"


def _num(x, spec: str) -> str:
    return "-" if x is None or isinstance(x, bool) else format(x, spec)
