"""Two run folders compared (``etar-bench diff RUN_A RUN_B``): their results side by side,
and their recordings compared as the equivalence tests compare them.

The recordings: file by file (by name, ``recordings/*.mcap``), every message as
``services.recordings.reader.recorded_content`` takes it (``tests/e2e/test_scenarios.py``
holds two transports to it): per (topic, seq), the payload without ``sent_ns``, the
wall-clock and visual topics left out.  Two runs of one seed compare equal whatever their
run ids, transports or hosts.  The first difference named is that of the first file (in
name order: the demonstrations, then the reproductions) that differs, at its earliest
robot cycle (seq), messages of one cycle in the order run A recorded them: the file, the
topic, the seq and the fields that differ with both values, or the file or message that
only one run has.

The results: report.json's ``summary`` (phases chosen, successes, accuracy, ...), the
scenario, its seed and clock, the error, and each episode's result; what the wall clock
or the run's identity decides is shown and not compared.  ``DiffResult.same``: the
recorded content and the compared results are equal.

Not compared (``IGNORED``, which the command's help prints).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from services.recordings.format import WALL_CLOCK_TOPICS
from services.recordings.reader import compared_messages
from services.results.folder import kept_recordings, read_report, report_episodes
from services.results.info import run_scenario
from services.runtime.visual_topics import SCHEMA_NAMES as VISUAL_SCHEMA_NAMES

IGNORED = (
    "sent_ns, every message's publish time on the host's CLOCK_MONOTONIC",
    f"the wall-clock topics {', '.join(sorted(WALL_CLOCK_TOPICS))} (wall durations, loop timing, the services' "
    "log lines)",
    f"the visual topics {', '.join(sorted(VISUAL_SCHEMA_NAMES))} (derived by the recorder from the newest "
    "messages it has, which over a network depends on the order of arrival)",
    "the run id (in the key expressions and the metadata record, in no payload compared)",
    "log and publish times, the metadata record (start, model path), the scenario attachment, the chunking",
    "in report.json: the run id, the transport and its engine, the provenance, every wall-clock figure (wall_seconds, "
    "episode_wall_seconds, real_time_factor) and the timing",
    "in model.json (compared as a digest of the rest): the fit's seconds, the note of what made it and the "
    "demonstrations' folders",
)
IGNORED_TEXT = "Not compared:\n" + "\n".join(f"  - {line}" for line in IGNORED)

# report.json summary fields the wall clock decides: shown, not compared
WALL_CLOCK_SUMMARY = frozenset({"episode_wall_seconds", "real_time_factor"})
_SHOWN_FIELDS = 3  # fields of a differing message named in first_difference


class DiffError(ValueError):
    """A path that is not a run folder, naming it."""


@dataclass
class FileDiff:
    """One recording of either run: its messages and how many differ."""

    name: str
    in_a: bool
    in_b: bool
    messages_a: int = 0  # messages compared (wall-clock and visual topics left out)
    messages_b: int = 0
    changed: int = 0  # (topic, seq) whose payloads differ
    only_a: int = 0  # (topic, seq) only run A recorded
    only_b: int = 0
    complete_a: bool | None = None
    complete_b: bool | None = None
    first: str | None = None  # the first difference in this file

    @property
    def same(self) -> bool:
        return self.in_a and self.in_b and not (self.changed or self.only_a or self.only_b)


@dataclass
class Row:
    """One line of the results table."""

    name: str
    a: object
    b: object
    compared: bool = True  # False: shown, not compared (wall clock, identity)

    @property
    def differs(self) -> bool:
        return self.compared and self.a != self.b


@dataclass
class DiffResult:
    a: str
    b: str
    files: list[FileDiff] = field(default_factory=list)
    rows: list[Row] = field(default_factory=list)

    @property
    def content_same(self) -> bool:
        return all(f.same for f in self.files)

    @property
    def results_same(self) -> bool:
        return not any(r.differs for r in self.rows)

    @property
    def same(self) -> bool:
        return self.content_same and self.results_same

    @property
    def first_difference(self) -> str | None:
        """The first recorded message (or file) that differs; if none, the first result."""
        for f in self.files:
            if not f.same:
                return f.first
        for r in self.rows:
            if r.differs:
                where = r.name if r.name == "model.json" else f"report.json {r.name}"
                return f"{where}: {_show(r.a)} in A, {_show(r.b)} in B"
        return None

    @property
    def results_table(self) -> str:
        width = max([len(r.name) for r in self.rows] + [5])
        wa = max([len(_show(r.a)) for r in self.rows] + [1])
        wb = max([len(_show(r.b)) for r in self.rows] + [1])
        lines = [f"{'':<{width}}  {'A':<{wa}}  B"]
        for r in self.rows:
            mark = "differs" if r.differs else ("(not compared)" if not r.compared and r.a != r.b else "")
            lines.append(f"{r.name:<{width}}  {_show(r.a):<{wa}}  {_show(r.b):<{wb}}  {mark}".rstrip())
        return "\n".join(lines)

    def text(self) -> str:
        lines = [f"A: {self.a}", f"B: {self.b}"]
        compared = sum(f.messages_a for f in self.files)
        if self.same:
            lines.append(f"SAME: {len(self.files)} recording(s), {compared} messages of A compared, the same; "
                         "the results compared are the same")
        else:
            what = [] if self.content_same else ["the recorded content"]
            what += [] if self.results_same else ["the results"]
            lines.append(f"DIFFERENT ({' and '.join(what)}): first difference: {self.first_difference}")
        lines += ["", "recordings (messages compared in A / B; (topic, seq) differing, only in A, only in B):"]
        w = max([len(f.name) for f in self.files] + [4])
        for f in self.files:
            if not (f.in_a and f.in_b):
                lines.append(f"  {f.name:<{w}}  only in {'A' if f.in_a else 'B'}")
                continue
            state = "same" if f.same else f"{f.changed} differ, {f.only_a} only in A, {f.only_b} only in B"
            cut = [x for x, c in (("A", f.complete_a), ("B", f.complete_b)) if c is False]
            lines.append(f"  {f.name:<{w}}  {f.messages_a:>7} / {f.messages_b:<7}  {state}"
                         + (f"  (incomplete in {' and '.join(cut)})" if cut else ""))
        if not self.files:
            lines.append("  none in either run")
        lines += ["", "results:", *("  " + line for line in self.results_table.splitlines()), "", IGNORED_TEXT]
        return "\n".join(lines) + "\n"

    def to_dict(self) -> dict:
        return {"a": self.a, "b": self.b, "same": self.same, "content_same": self.content_same,
                "results_same": self.results_same, "first_difference": self.first_difference,
                "files": [dict(vars(f), same=f.same) for f in self.files],
                "results": [{"name": r.name, "a": r.a, "b": r.b, "compared": r.compared, "differs": r.differs}
                            for r in self.rows],
                "ignored": list(IGNORED)}


def diff_runs(a, b) -> DiffResult:
    """Run folders ``a`` and ``b`` compared (module docstring).  DiffError if either is not a
    run folder; RecordingError (naming the file) if a recording is not MCAP or is damaged."""
    run_a, run_b = _run_folder(a), _run_folder(b)
    result = DiffResult(str(run_a), str(run_b))
    report_a, report_b = read_report(run_a, required=False), read_report(run_b, required=False)
    for run, report in ((run_a, report_a), (run_b, report_b)):
        _named_recordings_present(run, report)
    result.rows = _result_rows(run_a, report_a, run_b, report_b)
    names = sorted({p.name for run in (run_a, run_b) for p in (run / "recordings").glob("*.mcap")})
    for name in names:
        fa, fb = run_a / "recordings" / name, run_b / "recordings" / name
        if not (fa.exists() and fb.exists()):
            f = FileDiff(name, fa.exists(), fb.exists())
            f.first = f"{name}: only in {'A' if f.in_a else 'B'} ({run_a if f.in_a else run_b})"
            result.files.append(f)
            continue
        result.files.append(_compare(name, recording_content(fa), recording_content(fb)))
    return result


# ---------------------------------------------------------------------------
# the recordings
# ---------------------------------------------------------------------------


@dataclass
class Content:
    """What the seed determines of one recording: per (topic, seq) the payloads without
    ``sent_ns`` as ``recorded_content`` writes them (JSON, keys sorted), and where each key
    first appears in the file's log-time order."""

    messages: dict[tuple[str, int], list[str]]
    order: dict[tuple[str, int], int]
    count: int
    complete: bool

    def rows(self) -> list[tuple[str, int, str]]:
        """The same list ``recorded_content`` gives for this file."""
        return sorted((topic, seq, p) for (topic, seq), ps in self.messages.items() for p in ps)


def recording_content(path) -> Content:
    """One recording as ``recorded_content`` compares it, keyed for finding the first
    difference (one file at a time: two runs' recordings need not be in memory at once)."""
    rows, complete = compared_messages(path)
    messages: dict[tuple[str, int], list[str]] = {}
    order: dict[tuple[str, int], int] = {}
    for topic, seq, text in rows:
        key = (topic, seq)
        messages.setdefault(key, []).append(text)
        order.setdefault(key, len(order))
    return Content(messages, order, len(rows), complete)


def _compare(name: str, a: Content, b: Content) -> FileDiff:
    f = FileDiff(name, True, True, messages_a=a.count, messages_b=b.count, complete_a=a.complete,
                 complete_b=b.complete)
    first, first_rank = None, None
    for key in a.messages.keys() | b.messages.keys():
        pa, pb = a.messages.get(key), b.messages.get(key)
        if pa is not None and pb is not None and sorted(pa) == sorted(pb):
            continue
        if pb is None:
            f.only_a += 1
        elif pa is None:
            f.only_b += 1
        else:
            f.changed += 1
        # the earliest cycle; within it, run A's order (B's for what A lacks, after A's)
        rank = (key[1], a.order[key] if key in a.order else len(a.order) + b.order[key])
        if first_rank is None or rank < first_rank:
            first, first_rank = key, rank
    if first is not None:
        f.first = _describe_difference(name, first, a.messages.get(first), b.messages.get(first))
    return f


def _describe_difference(name: str, key: tuple[str, int], pa: list | None, pb: list | None) -> str:
    topic, seq = key
    where = f"{name} {topic} seq {seq}"
    if pa is None or pb is None:
        return f"{where}: only in {'A' if pb is None else 'B'}"
    if len(pa) != 1 or len(pb) != 1:
        return f"{where}: {len(pa)} message(s) in A, {len(pb)} in B"
    try:
        da, db = json.loads(pa[0]), json.loads(pb[0])
    except ValueError:
        return f"{where}: payloads differ"
    fields = _field_differences(da, db)
    shown = "; ".join(fields[:_SHOWN_FIELDS])
    more = f"; and {len(fields) - _SHOWN_FIELDS} more field(s)" if len(fields) > _SHOWN_FIELDS else ""
    return f"{where}: {shown}{more}" if fields else f"{where}: payloads differ"


def _field_differences(a, b, name: str = "") -> list[str]:
    """'field: A vs B' for every field that differs; a list by its first differing entry."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in list(a) + [k for k in b if k not in a]:
            sub = f"{name}.{k}" if name else str(k)
            if k not in a or k not in b:
                out.append(f"{sub}: {_show(a.get(k, '(absent)'))} in A, {_show(b.get(k, '(absent)'))} in B")
            elif a[k] != b[k] or json.dumps(a[k]) != json.dumps(b[k]):
                out += _field_differences(a[k], b[k], sub)
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b) and a:
        idx = [i for i, (x, y) in enumerate(zip(a, b)) if json.dumps(x) != json.dumps(y)]
        if idx and not isinstance(a[idx[0]], (dict, list)):
            i = idx[0]
            return [f"{name}[{i}]: {_show(a[i])} in A, {_show(b[i])} in B ({len(idx)} of {len(a)} entries differ)"]
    return [f"{name}: {_show(a)} in A, {_show(b)} in B"]


def _show(x, limit: int = 60) -> str:
    if x is None:
        return "-"
    text = repr(x) if isinstance(x, float) else (x if isinstance(x, str) else json.dumps(x))
    return text if len(text) <= limit else text[:limit - 3] + "..."


# ---------------------------------------------------------------------------
# the results
# ---------------------------------------------------------------------------


def _run_folder(path) -> Path:
    p = Path(path)
    if not p.exists():
        raise DiffError(f"{p}: no such folder")
    if not p.is_dir():
        raise DiffError(f"{p}: a file; diff compares two run folders")
    if not (p / "report.json").exists() and not (p / "recordings").is_dir():
        raise DiffError(f"{p}: not a run folder (no report.json, no recordings/)")
    if (p / "recordings").exists() and not (p / "recordings").is_dir():
        raise DiffError(f"{p / 'recordings'}: not a folder")
    return p


def _named_recordings_present(run: Path, report: dict) -> None:
    """Every recording the run's report names is there: two runs that both lost theirs
    must not compare as the same (nothing would be compared); a run that kept none by choice
    (``kept_recordings``) is compared by its results."""
    if not kept_recordings(run):
        return
    for kind in ("demonstrations", "reproductions", "served"):
        for e in report_episodes(report, kind, run / "report.json"):
            path = e.get("path") if isinstance(e, dict) else None
            if isinstance(path, str) and not (run / path).is_file():  # an absolute path stays itself
                raise DiffError(f"{run / path}: named by {run / 'report.json'} ({kind}), missing")


def _transport(report: dict):
    """The transport a report names, with its engine in one process ('inproc (fused)')."""
    engine = report.get("engine")
    return f"{report.get('transport')} ({engine})" if engine else report.get("transport")


def _result_rows(run_a: Path, ra: dict, run_b: Path, rb: dict) -> list[Row]:
    sa, sb = run_scenario(run_a), run_scenario(run_b)
    rows = [Row("scenario", ra.get("scenario", sa.get("name")), rb.get("scenario", sb.get("name"))),
            Row("seed", sa.get("seed"), sb.get("seed")),
            Row("clock", (ra.get("environment") or {}).get("clock", sa.get("clock")),
                (rb.get("environment") or {}).get("clock", sb.get("clock"))),
            Row("error", ra.get("error"), rb.get("error")),
            Row("run_id", ra.get("run_id"), rb.get("run_id"), compared=False),
            Row("transport", _transport(ra), _transport(rb), compared=False)]
    pa, pb = ra.get("provenance") or {}, rb.get("provenance") or {}
    for k in ("version", "commit"):
        if k in pa or k in pb:
            rows.append(Row(f"provenance.{k}", pa.get(k), pb.get(k), compared=False))
    summary_a, summary_b = ra.get("summary") or {}, rb.get("summary") or {}
    flat_a, flat_b = _flat(summary_a), _flat(summary_b)
    for k in list(flat_a) + [k for k in flat_b if k not in flat_a]:
        rows.append(Row(f"summary.{k}", flat_a.get(k), flat_b.get(k), compared=k not in WALL_CLOCK_SUMMARY))
    for kind in ("demonstrations", "reproductions"):
        ea, eb = ra.get(kind) or [], rb.get(kind) or []
        for i in range(max(len(ea), len(eb))):
            rows.append(Row(f"{kind[:-1]} {i}", _episode(ea[i]) if i < len(ea) else None,
                            _episode(eb[i]) if i < len(eb) else None))
    rows.append(Row("model.json", _model(run_a), _model(run_b)))
    rows.append(Row("wall_seconds", _round(ra.get("wall_seconds")), _round(rb.get("wall_seconds")), compared=False))
    return rows


def _model(run: Path) -> str | None:
    """The run's learned (or stored) model as what the seed decides of it: a digest of its
    JSON without the fit's wall-clock seconds, the note of what made it and the folders of
    the demonstrations it learned from (their names stay)."""
    import hashlib

    path = run / "model.json"
    if not path.exists():
        return None
    try:
        model = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as exc:  # two runs' unreadable models must not compare equal
        raise DiffError(f"{path}: not a JSON model ({type(exc).__name__}: {exc})") from None
    if isinstance(model, dict):
        fit, meta = model.get("fit"), model.get("metadata")
        if isinstance(fit, dict):
            fit.pop("seconds", None)
        if not isinstance(meta, dict):
            meta = {}
        meta.pop("made_by", None)
        if isinstance(meta.get("demonstrations"), list):  # where each run's folder is: by name only
            meta["demonstrations"] = [Path(str(d)).name for d in meta["demonstrations"]]
    text = json.dumps(model, sort_keys=True)
    return f"sha256 {hashlib.sha256(text.encode()).hexdigest()[:12]}"


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _episode(entry) -> str | None:
    """An episode's result as report.json has it, in a line: what the seed decides."""
    if not isinstance(entry, dict):
        return None
    parts = [str(entry.get("reason")), f"{entry.get('sim_seconds')} s"]
    if "success" in entry:
        parts.append("success" if entry["success"] else "failed")
    acc = (entry.get("phases") or {}).get("accuracy")
    if acc is not None:
        parts.append(f"accuracy {acc!r}")
    return ", ".join(parts)


def _round(x):
    return round(x, 2) if isinstance(x, float) else x
