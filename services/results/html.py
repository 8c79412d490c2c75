"""A run's report as one self-contained HTML page: ``RUN_DIR/report.html``.

The scenario, the error if the run failed, the phase-count selection, the
reproductions, the timing, and every figure (``services.results.figures`` and the
timing plot) embedded as data: URIs, so the one file can be mailed, committed
or opened from anywhere.  Written from the report and its text as the run hands them
over, or as a finished run's folder holds them (report.json, report.txt), and the PNGs
beside them.
"""

from __future__ import annotations

import base64
import html
import time
from pathlib import Path

from services.results.figures import COMPARISON_FIGURE, FIGURES_DIR, write_figures
from services.results.folder import read_report
from services.results.record import RunRecord
from services.results.text import provenance_text
from services.runtime.files import FileWriteError, write_file

# what an earlier drawing of the figures and the page may have left
STALE_FILES = ("figures.error", "figures.skipped", "report.html", "report.html.error")

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; font-size: 0.9em; } td, th { padding: 2px 8px; text-align: right; }
th { background: #eee; } td.l, th.l { text-align: left; }
.error { background: #fdd; padding: 0.6em; border: 1px solid #c00; }
figure { margin: 1.2em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.85em; color: #555; }
pre { background: #f6f6f6; padding: 0.6em; overflow-x: auto; font-size: 0.8em; }
"""


def _e(x) -> str:
    return html.escape(str(x))


def _img(path: Path) -> str:
    data = base64.b64encode(path.read_bytes()).decode()
    return (f'<figure><img alt="{_e(path.stem)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{_e(path.name)}</figcaption></figure>")


def _table(head: list, rows: list, left: int = 1) -> str:
    th = "".join(f'<th class="{"l" if i < left else ""}">{_e(h)}</th>' for i, h in enumerate(head))
    body = "".join("<tr>" + "".join(f'<td class="{"l" if i < left else ""}">{_e(c)}</td>' for i, c in enumerate(r))
                   + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


def _fmt(x, spec=".3f"):
    return "-" if x is None else format(x, spec)


def render_html(r: dict, text: str | None, images: list[Path]) -> str:
    """The page of the report ``r`` (report.json's content), with its ``text`` (report.txt's;
    None: left out) and the PNG files ``images`` embedded."""
    s = r["summary"]
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>ETAR run {_e(r['run_id'])}</title>"
             f"<style>{STYLE}</style></head><body>",
             f"<h1>ETAR testbench run {_e(r['run_id'])}</h1>",
             f"<p>scenario <b>{_e(r['scenario'])}</b> ({_e(r['source'])}); clock {_e(r['environment']['clock'])}; "
             f"transport {_e(r.get('transport', '-'))}; "
             f"{r['environment']['cpus']} CPUs, kernel {_e(r['environment']['kernel'])}; "
             f"{r['wall_seconds']:.1f} s wall</p>"]
    if r.get("provenance"):
        parts.append(f"<p class='provenance'>{_e(provenance_text(r['provenance']))}</p>")
    if r.get("error"):
        parts.append(f"<p class='error'>RUN FAILED: {_e(r['error'])}</p>")
    parts.append("<h2>Result</h2>")
    parts.append(_table(["", ""], [
        ["phases chosen", s.get("phases_chosen")],
        ["reproductions reaching the goal with bounded force", f"{s.get('successes')} of {s.get('reproductions')}"],
        ["online phase accuracy", _fmt(s.get("online_phase_accuracy"), ".4f")],
        ["mean transition error [s]", _fmt(s.get("mean_transition_error_s"))],
        ["real-time factor over the episodes", _fmt(s.get("real_time_factor"), ".2f")]]))
    sel = (r.get("learning") or {}).get("selection") or {}
    if sel:
        parts.append("<h2>Number of phases</h2>")
        rows = []
        for i, d in enumerate(sel.get("per_demonstration", [])):
            rows.append([f"demonstration {i}"] + [f"{d['scores'][k]:.0f}" for k in sorted(d["scores"], key=int)]
                        + [d["best"]])
        if sel.get("scores"):
            rows.append(["pooled"] + [f"{sel['scores'][k]:.0f}" for k in sorted(sel["scores"], key=int)]
                        + [sel["best"]])
        ks = sorted((sel.get("scores") or (sel.get("per_demonstration") or [{}])[0].get("scores") or {}), key=int)
        if rows:
            parts.append(_table(["", *[f"K={k}" for k in ks], "best"], rows))
        parts.append(f"<p>chosen: {_e(sel.get('best'))} ({_e(sel.get('criterion'))}"
                     f"{', ' + _e(sel['method']) if sel.get('method') else ''})</p>")
    repro = r.get("reproductions") or []
    if repro:
        parts.append("<h2>Reproductions</h2>")
        parts.append(_table(
            ["#", "side", "result", "peak F [N]", "phase accuracy", "transition error [s]", "sim [s]", "wall [s]"],
            [[rp["index"], rp["side"], rp["reason"], f"{rp['peak_contact_force']:.1f}",
              _fmt((rp.get("phases") or {}).get("accuracy"), ".3f"),
              _fmt((rp.get("phases") or {}).get("mean_transition_error_s")),
              f"{rp['sim_seconds']:.1f}", f"{rp['wall_seconds']:.1f}"] for rp in repro], left=3))
    loop = (r.get("timing") or {}).get("robot_loop") or {}
    if loop:
        parts.append("<h2>Timing</h2>")
        if r["environment"]["clock"] == "lockstep":
            parts.append(f"<p>simulated: {loop.get('cycles')} FRI cycles of 1 ms in lockstep, each waiting for its "
                         "answers, so every deadline is met by construction. The latencies in the text report are "
                         "the host's wall clock running the simulation, not the system's timing.</p>")
        else:
            parts.append(f"<p>robot loop: {loop.get('cycles')} cycles, {loop.get('deadline_misses')} deadline misses, "
                         f"longest run {loop.get('longest_miss_run')}</p>")
    if images:
        parts.append("<h2>Figures</h2>")
        parts += [_img(p) for p in images]
    if text is not None:
        parts.append(f"<h2>Full text report</h2><pre>{_e(text)}</pre>")
    # a browser says whether every figure decoded: body[data-images] = "loaded/all" after load
    parts.append("<script>window.addEventListener('load', function () { var im = document.images, ok = 0; "
                 "for (var i = 0; i < im.length; i++) { if (im[i].complete && im[i].naturalWidth > 0) ok++; } "
                 "document.body.setAttribute('data-images', ok + '/' + im.length); });</script>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write_html(run_dir, report: dict | None = None, text: str | None = None) -> Path:
    """report.html in ``run_dir``: the run's ``report`` and ``text`` as the run just wrote
    them, or (``report`` None) as its folder holds them; every figure in the folder embedded."""
    run_dir = Path(run_dir)
    if report is None:
        report = read_report(run_dir)
        written = run_dir / "report.txt"
        text = written.read_text() if written.is_file() else None
    figures = sorted((run_dir / FIGURES_DIR).glob("*.png")) if (run_dir / FIGURES_DIR).is_dir() else []
    extra = [run_dir / "timing.png"] if (run_dir / "timing.png").is_file() else []
    return write_file(run_dir / "report.html", render_html(report, text, figures + extra))


def _note(path: Path, text: str) -> None:
    """Why a figure or the page is missing; on a disk too full for that too, the reason
    was the run's to say (its figures are extras of a report already written)."""
    try:
        write_file(path, text)
    except FileWriteError:
        pass


def write_figures_and_page(run_dir, progress=None, run: RunRecord | None = None, ahead: tuple | None = None) -> str:
    """The thesis' figures (``RUN_DIR/figures/``) and report.html after a run's report; one
    line saying what was written.  ``run``: the record of the run just reported, whose
    report, text and decoded recordings they are drawn from (None: the folder's);
    ``ahead``: the figures this run drew while it reproduced (``write_figures``').  A
    figure that cannot be drawn must not cost the run its report: the reason goes in
    figures.error, with every recording found damaged (figures.skipped: what was left out)."""
    run_dir = Path(run_dir)
    t = time.monotonic()
    # the page embeds every figure in the folder: none may be left from an earlier drawing
    # (a BIC figure of a run that has since fixed its phase count); etar-bench compare's
    # figure is not the run's to redraw, nor those this run drew already
    keep = {COMPARISON_FIGURE, *(Path(p).name for p in (ahead[0] if ahead is not None else ()))}
    for stale in [*(run_dir / FIGURES_DIR).glob("*.png"), *(run_dir / n for n in STALE_FILES)]:
        if stale.name not in keep:
            stale.unlink(missing_ok=True)
    try:
        written, skipped, damaged = write_figures(run_dir, progress=progress, run=run, ahead=ahead)
    except Exception as exc:
        _note(run_dir / "figures.error", f"{type(exc).__name__}: {exc}\n")
        written, skipped, damaged = [], [f"{type(exc).__name__}: {exc}"], []
    if damaged:  # figures from what could be read, and the folder says what could not
        _note(run_dir / "figures.error", "".join(f"damaged recording {d}\n" for d in damaged))
    if skipped:
        _note(run_dir / "figures.skipped", "".join(f"{why}\n" for why in skipped))
    try:
        if run is None:
            write_html(run_dir)
        else:
            write_html(run_dir, run.report, run.report_text)
    except Exception as exc:
        _note(run_dir / "report.html.error", f"{type(exc).__name__}: {exc}\n")
    page = "report.html" if (run_dir / "report.html").is_file() and not (run_dir / "report.html.error").exists() \
        else "no report.html (report.html.error says why)"
    return (f"figures: {len(written)} in {run_dir / FIGURES_DIR}, {page} ({time.monotonic() - t:.1f} s)"
            + (f"; {len(skipped)} left out (figures.skipped)" if skipped else ""))
