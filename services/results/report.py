"""The run report: ``report.json`` for machines, ``report.txt`` for people.

Everything is measured from the run's recordings and the services' own
statistics:

- learning: the number of phases chosen and the BIC/AIC table;
- per reproduction: reached the goal, peak contact force, and the online
  estimator's phase accuracy and transition-time error against the
  simulator's ground truth (learned phases are mapped to true phases once, on
  the demonstrations, never per reproduction);
- timing: the robot loop's deadline misses and per-link latency percentiles
  (publish -> recorder receive, one host, CLOCK_MONOTONIC), the FRI answer
  latency, and the environment (kernel, CPUs, clock mode, SCHED_FIFO).
"""

from __future__ import annotations

import json
import os
import platform
from dataclasses import asdict
from pathlib import Path

import numpy as np

from robot_sim.cycle import FRI_CYCLE_NS
from services.results.decoding import DecodedEpisode, EpisodeReading, decode_episodes
from services.results.folder import strict_json
from services.results.record import EpisodeRecord, RunRecord
from services.runtime.messages import HOLD_WATCH_S
from services.results.text import pooled_histogram, histograms_text, render_text
from services.runtime.files import FileWriteError, write_file, write_via

QUALITY_NAMES = ("UNACCEPTABLE", "BAD", "OK", "PERFECT")
STATE_NAMES = ("OFF", "MON", "CMD")
MAX_TRANSITIONS = 200  # per episode in report.json; a flapping link gets its count, not a list of thousands


def _changes(t, v) -> list:
    if len(v) == 0:
        return []
    at = np.concatenate([[0], np.flatnonzero(np.diff(v)) + 1])
    return [[round(float(t[i]), 3), int(v[i])] for i in at]


def fri_quality_timeline(t, q, state) -> dict:
    """FRI quality and state over one episode, as the robot published them every cycle:
    the changes ([simulated time s, value]; times are the robot's clock, not the
    episode's), the time spent at each quality, and how often PERFECT was lost."""
    if len(t) == 0:
        return {"cycles": 0}
    dt = float(np.median(np.diff(t))) if len(t) > 1 else FRI_CYCLE_NS / 1e9
    quality, states = _changes(t, q), _changes(t, state)
    drops = int(np.sum((q[:-1] == 3) & (q[1:] < 3)))
    perfect = np.flatnonzero(q == 3)
    cmd = np.flatnonzero(state == 2)
    return {
        "cycles": int(len(t)), "start_s": round(float(t[0]), 3), "end_s": round(float(t[-1]), 3),
        "seconds_at": {name: round(float(np.sum(q == i)) * dt, 3) for i, name in enumerate(QUALITY_NAMES)},
        "seconds_in_state": {name: round(float(np.sum(state == i)) * dt, 3) for i, name in enumerate(STATE_NAMES)},
        "first_perfect_s": round(float(t[perfect[0]]), 3) if perfect.size else None,
        "first_cmd_s": round(float(t[cmd[0]]), 3) if cmd.size else None,
        "drops_from_perfect": drops,
        "quality_changes": quality[:MAX_TRANSITIONS], "quality_changes_total": len(quality),
        "state_changes": states[:MAX_TRANSITIONS], "state_changes_total": len(states),
    }


def environment(clock: str, fifo: bool, profile: dict | None = None, services: dict | None = None) -> dict:
    """``profile``: the realtime profile's request and grant (services.run.realtime_profile);
    ``services``: what each service said at the end (its SCHED_FIFO priority, its CPUs)."""
    per_service = {role: {"sched_fifo": st.get("sched_fifo", False), "cpus": st.get("cpus")}
                   for role, st in (services or {}).items() if isinstance(st, dict) and "sched_fifo" in st}
    return {"kernel": platform.release(), "machine": platform.machine(), "cpus": os.cpu_count(),
            "python": platform.python_version(), "clock": clock, "sched_fifo": fifo,
            "realtime_profile": profile, "services": per_service}


# a realtime run that misses more than this share of its cycles did not hold its clock:
# it is failed, not reported as a result (the lab's own runs aim at none at all)
REALTIME_MISS_LIMIT = 0.01
CLOCK_NOT_HELD = "the realtime clock was not held"  # how clock_not_held's line begins
FRI_CHAIN_LINKS = ("robot/state -> impedance_commander", "robot/command -> robot", "robot/contact -> ft_sensor",
                   "ft/wrench -> phase_estimator", "estimator/phase -> impedance_commander",
                   "robot/state -> teacher", "teacher/wrench -> robot")


def clock_not_held(demonstrations, reproductions, loops, received) -> str | None:
    """Why a realtime run did not hold its 1 kHz clock, in one line, or None: the robot
    loop missing more than REALTIME_MISS_LIMIT of its deadlines in any episode, a
    reproduction whose FRI link missed more than that share, never reached command mode
    or was dropped from it (quality below OK: a burst of misses, however few in all);
    with the chain's latest link (p99 at its receiver)."""
    problems = []
    kinds = [("demonstration", i) for i in range(len(demonstrations))] + \
            [("reproduction", i) for i in range(len(reproductions))]
    for (kind, i), lp in zip(kinds, loops):
        if lp.get("cycles") and lp["misses"] / lp["cycles"] > REALTIME_MISS_LIMIT:
            problems.append(f"{kind} {i}: the robot loop missed {lp['misses']} of {lp['cycles']} deadlines "
                            f"({lp['misses'] / lp['cycles']:.1%})")
    for rp in reproductions:
        f, fq = rp.get("fri") or {}, rp.get("fri_quality") or {}
        total = f.get("answered", 0) + f.get("missed", 0)
        why = []
        if fq and fq.get("first_cmd_s") is None:
            why.append("FRI never reached command mode")
        if f.get("command_mode_left"):
            why.append(f"the KRC dropped command mode {f['command_mode_left']} time(s) (FRI quality below OK)")
        if total and f["missed"] / total > REALTIME_MISS_LIMIT:
            why.append(f"{f['missed']} of {total} FRI cycles unanswered in time ({f['missed'] / total:.1%})")
        if why:
            problems.append(f"reproduction {rp['index']}: " + ", ".join(why))
    if not problems:
        return None
    chain = [(v["latency"]["p99_us"], name) for name, v in received.items()
             if name in FRI_CHAIN_LINKS and (v.get("latency") or {}).get("count")]
    late = f"; latest link {max(chain)[1]} (p99 {max(chain)[0]:.0f} us)" if chain else ""
    more = f" (and {len(problems) - 2} more)" if len(problems) > 2 else ""
    return (f"{CLOCK_NOT_HELD} (limit {REALTIME_MISS_LIMIT:.0%} of cycles): "
            + "; ".join(problems[:2]) + more + late)


def commander_held(reproductions) -> str | None:
    """The run failed if the commander had to hold the arm: one line on the first hold."""
    for rp in reproductions:
        h = rp.get("hold")
        if h:
            age = h["seq"] - h["estimate_seq"] if h.get("estimate_seq", -1) >= 0 else None
            if h["reason"].startswith("wrench_"):
                why = f"the phase estimate of cycle {h['estimate_seq']} could not use its wrench"
            else:
                why = f"the last phase estimate was {age} cycles old" if age is not None else "no phase estimate yet"
            return (f"reproduction {rp['index']}: the impedance commander held the arm {h['at_s']:.3f} s in "
                    f"(cycle {h['seq']}, {h['reason']}: " + why
                    + f"); held {h.get('cycles', 0)} cycles in all (the robot ends the episode after "
                      f"{HOLD_WATCH_S:g} s in one), while held the tcp moved at most "
                      f"{1e3 * h['max_displacement_m']:.1f} mm and the contact force peaked at "
                      f"{h['peak_contact_force']:.1f} N")
    return None


def _in_run(path, run_dir: Path) -> str | None:
    """A path for report.json: relative to the run directory when it lies inside it
    (a run directory can be moved or committed), absolute otherwise."""
    if path is None:
        return None
    p = Path(path)
    try:
        return str(p.relative_to(run_dir))
    except ValueError:
        return str(p)


def _parts_of(episode: EpisodeRecord, run_dir: Path) -> dict:
    """An episode recorded in parts (its recorder restarted): the further files and the
    cycles no part holds."""
    rec = episode.recording or {}
    if not rec.get("parts"):
        return {}
    gaps = [dict(g, part=_in_run(g["part"], run_dir), next_part=_in_run(g["next_part"], run_dir))
            for g in rec.get("gaps", [])]
    return {"recording_parts": [_in_run(p, run_dir) for p in rec["parts"]], "recording_gaps": gaps}


def reproduction_figures(repro: list) -> dict:
    """Success, online phase accuracy, transition-time error and peak force of some reproductions."""
    updates = sum(r["phases"].get("updates", 0) for r in repro)
    correct = sum(r["phases"].get("correct", 0) for r in repro)
    errors = [e for r in repro for e in r["phases"].get("transition_errors_s", [])]
    return {"reproductions": len(repro), "successes": sum(r["success"] for r in repro),
            "success_rate": sum(r["success"] for r in repro) / len(repro) if repro else None,
            "online_phase_accuracy": correct / updates if updates else None,
            "mean_transition_error_s": float(np.mean(errors)) if errors else None,
            "peak_contact_force_n": max((r["peak_contact_force"] for r in repro), default=None),
            "mean_peak_contact_force_n": float(np.mean([r["peak_contact_force"] for r in repro])) if repro else None}


def by_model(repro: list) -> dict:
    """``reproduction_figures`` per model, when reproductions name the model that drove them."""
    names = list(dict.fromkeys(r["model"] for r in repro if r.get("model")))
    return {name: reproduction_figures([r for r in repro if r.get("model") == name]) for name in names}


def episode_readings(run: RunRecord) -> list[EpisodeReading]:
    """What the report takes from each recording, demonstrations, reproductions and served
    episodes in that order: every one's measures, and when the run draws its figures (with
    a model to draw them with) what they draw: the demonstrations' arrays, the first
    reproduction's trace."""
    learning = run.learning
    view = run.figures if learning.model is not None else None

    def reading(e: EpisodeRecord, **what) -> EpisodeReading:
        return EpisodeReading(e.path, tuple((e.recording or {}).get("parts", ())), **what)

    # each reproduction is judged by the phase mapping of the model that drove it
    return ([reading(d, demonstration=view) for d in run.demonstrations]
            + [reading(r, phase_to_truth=r.phase_to_truth or learning.phase_to_truth, trace=None if i else view)
               for i, r in enumerate(run.reproductions)]
            + [reading(e) for e in run.served])


def _gathered(run: RunRecord, decoded: list[DecodedEpisode]) -> tuple[dict, dict, dict, dict]:
    """The decoded recordings as the report reads them: per topic every episode's links;
    by recording its reproduction's phase scores, FRI quality series and undecodable
    messages.  What the figures draw goes into each episode's record."""
    links, phases_of, quality, undecodable = {}, {}, {}, {}
    for episode, d in zip(run.demonstrations + run.reproductions + run.served, decoded):
        episode.figure_data = d.figure_data
        if not d.readable:
            continue
        quality[d.path], undecodable[d.path] = d.fri_quality, d.undecodable
        for topic, v in d.links.items():
            links.setdefault(topic, []).append(v)
        if d.phases is not None:
            phases_of[d.path] = d.phases
    return links, phases_of, quality, undecodable


def _reproductions(run: RunRecord, phases_of: dict, timelines: dict, undecodable: dict) -> list[dict]:
    """report.json's entry of each reproduction: its result, and its phases as scored."""
    out = Path(run.out)
    repro = []
    for r in run.reproductions:
        s = r.summary
        phases = phases_of.get(r.path, {})
        # a hold run (stop_at_goal: false) keeps going after the goal: the commander said when
        reached = (s["reason"] == "goal_reached" or s.get("goal_reached_at_s", -1.0) >= 0) \
            and not s["reason"].startswith(("lost:", "unanswered:"))  # an episode a lost service ended failed
        bounded = s["peak_contact_force"] <= r.max_contact_force
        repro.append(dict(index=len(repro), path=_in_run(r.path, out), side=r.side, start=r.start,
                          model=r.model, reason=s["reason"],
                          reached_goal=reached, peak_contact_force=s["peak_contact_force"],
                          bounded_force=bounded, success=reached and bounded, sim_seconds=s["sim_seconds"],
                          wall_seconds=s["wall_seconds"], final_position=s["final_position"], phases=phases,
                          goal_reached_at_s=s.get("goal_reached_at_s", -1.0), hold=s.get("hold"), fri=s.get("fri"),
                          fri_quality=timelines.get(r.path, {}),
                          undecodable_messages=undecodable.get(r.path, 0),
                          **_parts_of(r, out)))
    return repro


def _demonstrations(run: RunRecord, timelines: dict, undecodable: dict) -> list[dict]:
    out = Path(run.out)
    return [dict(path=_in_run(d.path, out), side=d.side, start=d.start, reason=d.summary["reason"],
                 sim_seconds=d.summary["sim_seconds"], wall_seconds=d.summary["wall_seconds"],
                 fri=d.summary.get("fri"), fri_quality=timelines.get(d.path, {}),
                 undecodable_messages=undecodable.get(d.path, 0), **_parts_of(d, out))
            for d in run.demonstrations]


def _served(run: RunRecord, timelines: dict, undecodable: dict) -> dict:
    """etar-bench serve: what the lab's remote did (the KRL program's events, the link's
    states, time in command mode, the datagrams, any refusal or safety stop)."""
    if not run.served:
        return {}
    out = Path(run.out)
    return {"served": [dict(path=_in_run(e.path, out), start=e.start, reason=e.summary["reason"],
                            sim_seconds=e.summary["sim_seconds"], wall_seconds=e.summary["wall_seconds"],
                            peak_contact_force=e.summary["peak_contact_force"], safety=e.summary["safety"],
                            final_position=e.summary["final_position"], fri=e.summary.get("fri"),
                            wire=e.summary.get("wire"), fri_quality=timelines.get(e.path, {}),
                            undecodable_messages=undecodable.get(e.path, 0), **_parts_of(e, out))
                       for e in run.served]}


def _learning(run: RunRecord) -> dict:
    learning, out = run.learning, Path(run.out)
    return {"model": _in_run(learning.model_path, out), "seconds": learning.seconds,
            "selection": learning.selection,
            "phase_to_truth": learning.phase_to_truth, "goal": learning.goal,
            "models": {m.name: dict(asdict(m), path=_in_run(m.path, out)) for m in learning.models.values()},
            # every model against the demonstrations' true phases (with more than one)
            "offline": list(learning.offline),
            "demonstrations_read": [dict(path=_in_run(d["path"], out), samples=d["samples"])
                                    for d in learning.learned_from]}


def _received(run: RunRecord) -> dict:
    """Every link as its receiver measured it, named "topic -> role"."""
    received = {}
    for role, st_ in run.service_stats.items():
        for topic, v in (st_.get("links") or {}).items():
            received[f"{topic} -> {role}"] = v
    return received


def _timing(run: RunRecord, episodes: list, loops: list, links: dict, received: dict) -> dict:
    """report.json's timing: the robot loop, the links, the closed loop, FRI, the services."""
    link_summary = {}
    for t, vs in links.items():
        timed = [v for v in vs if "p50_us" in v]  # an episode whose every stamp of t was off the clock has none
        off = sum(v.get("off_clock", 0) for v in vs)
        row = {"p50_us": float(np.median([v["p50_us"] for v in timed])), "p99_us": float(max(v["p99_us"] for v in timed)),
               "max_us": float(max(v["max_us"] for v in timed))} if timed else {}
        if timed or off:
            link_summary[t] = dict(row, lost=sum(v["lost"] for v in vs), out_of_order=sum(v["out_of_order"] for v in vs),
                                   off_clock=off)
    closed = [lp.get("closed_loop_latency", {}) for lp in loops if lp.get("closed_loop_latency", {}).get("count")]
    return {
        # lockstep: simulated time waits for every answer, so every deadline is met by
        # construction and what follows is measured on the host's wall clock, not the
        # system's timing; realtime: the 1 kHz loop's own deadlines on the wall clock
        "basis": "host wall clock (lockstep)" if run.clock == "lockstep" else "wall clock (realtime)",
        "robot_loop": {"cycles": sum(lp["cycles"] for lp in loops),
                       "deadline_misses": sum(lp["misses"] for lp in loops),
                       "longest_miss_run": max((lp["longest_miss_run"] for lp in loops), default=0),
                       "per_episode": loops},
        "links_publish_to_recorder": link_summary,
        "links_received": received,
        "closed_loop": {"per_episode": closed,
                        "p99_us_max": max((c["p99_us"] for c in closed), default=None)},
        "fri": [e["fri"] for e in episodes],
        # what each service said about itself at the end (counters, the commander's sections)
        "services": {role: {k: v for k, v in (st_ or {}).items() if k not in ("links", "ok")}
                     for role, st_ in run.service_stats.items()},
    }


def write_report(run: RunRecord, exit_codes: dict, error: str | None, wall_seconds: float,
                 decoded: list = ()) -> dict:
    """report.json, report.txt, timing.txt and timing.png in the run's folder; the report.
    Each recording is decoded once (``episode_readings``; ``decoded``: those decoded as the run
    went, ``decode_episodes``); the report, its text and what the figures draw from each
    recording are left in ``run`` for the figures and the page."""
    decoded = decode_episodes(episode_readings(run), run.workers, decoded)
    links, phases_of, quality, undecodable = _gathered(run, decoded)
    timelines = {path: fri_quality_timeline(*series) for path, series in quality.items()}
    repro = _reproductions(run, phases_of, timelines, undecodable)
    overall = reproduction_figures(repro)
    episodes = ([d.summary for d in run.demonstrations] + [r.summary for r in run.reproductions]
                + [e.summary for e in run.served])
    loops = [e["loop"] for e in episodes if e.get("loop")]
    received = _received(run)
    sim_total = sum(e["sim_seconds"] for e in episodes)
    wall_total = sum(e["wall_seconds"] for e in episodes)
    if run.clock == "realtime" and error is None and loops:
        error = clock_not_held(run.demonstrations, repro, loops, received)
    if error is None:  # after the clock: a machine that could not hold it also starves the estimator
        error = commander_held(repro)
    report = strict_json({
        "scenario": run.scenario_name,
        "source": run.source,
        "run_id": run.run_id,
        "error": error,
        "wall_seconds": wall_seconds,
        "transport": run.transport,
        **({"engine": run.engine} if run.engine else {}),
        "wire": run.wire,
        # what made the run: the code (version, commit, uncommitted changes), the date, the
        # command line and the libraries' versions
        "provenance": run.provenance,
        "environment": environment(run.clock, any(loop.get("sched_fifo") for loop in loops), run.realtime_profile,
                                   run.service_stats),
        "paths": "relative to the folder of this report, unless absolute",
        "demonstrations": _demonstrations(run, timelines, undecodable),
        "learning": _learning(run),
        "reproductions": repro,
        **_served(run, timelines, undecodable),
        "summary": {
            "phases_chosen": (run.learning.selection or {}).get("best"),
            "reproductions": len(repro),
            "successes": overall["successes"],
            "online_phase_accuracy": overall["online_phase_accuracy"],
            "mean_transition_error_s": overall["mean_transition_error_s"],
            "simulated_seconds": sim_total,
            "episode_wall_seconds": wall_total,
            "real_time_factor": sim_total / wall_total if wall_total else None,
            # the same starts reproduced with each model (reproduce.transitions)
            "by_model": by_model(repro),
        },
        "timing": _timing(run, episodes, loops, links, received),
        "exit_codes": exit_codes,
        # services lost and started again by their restart policy (scenario 'restart:')
        "restarts": list(run.restarts),
        # where each service ran (services.transport.hosts), when the run was split across hosts
        "hosts": list(run.hosts),
    })
    text = render_text(report)
    _write(Path(run.out), report, text, loops, quality, run.clock)
    run.report, run.report_text = report, text
    return report


def _write(out: Path, report: dict, text: str, loops: list, quality: dict, clock: str) -> None:
    # report.json last: its presence says the report is whole (FileWriteError: none of it was)
    write_file(out / "report.txt", text)
    write_file(out / "timing.txt", histograms_text(loops))
    write_file(out / "report.json", json.dumps(report, indent=1, allow_nan=False) + "\n")
    for stale in ("timing.png", "timing.png.error"):
        (out / stale).unlink(missing_ok=True)
    if clock == "realtime":  # in lockstep its histograms are the host's, not the loop's timing
        try:
            write_via(out / "timing.png", lambda tmp: plot_timing(report, loops, quality, tmp))
        except Exception as exc:  # a picture must not cost the run its report
            try:
                write_file(out / "timing.png.error", f"{type(exc).__name__}: {exc}\n")
            except FileWriteError:
                pass


def plot_timing(report, loops, quality: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12, 7))
    for ax, (key, title) in zip(axes.ravel()[:3], (("lateness", "loop wake-up lateness"),
                                                   ("answer_latency", "FRI answer latency"),
                                                   ("closed_loop_latency", "closed-loop latency"))):
        h = pooled_histogram(loops, key)
        # the bins as one filled outline, not a bar patch each (a thousand bins a histogram)
        ax.stairs(h.counts, np.arange(h.counts.size + 1) * h.bin_ns / 1e3, fill=True)
        if h.counts.any():
            ax.set_yscale("log")
        ax.set_xlim(0, max(50.0, (np.flatnonzero(h.counts).max() + 2) * h.bin_ns / 1e3 if h.counts.any() else 50.0))
        ax.set_title(f"{title} (overflow >= {h.limit_ns / 1e6:.0f} ms: {h.overflow})")
        ax.set_xlabel("us (10 us bins)")
    ax = axes.ravel()[3]
    for path_, (t, q, _) in list(quality.items())[-4:]:
        if len(t):
            ax.step(t - t[0], q, where="post", label=Path(path_).stem)
    ax.set_yticks([0, 1, 2, 3], ["UNACC.", "BAD", "OK", "PERFECT"])
    ax.set_title("FRI quality over each episode")
    ax.set_xlabel("simulated time in episode [s]")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    fig.suptitle(f"run {report['run_id']} ({report['environment']['clock']})")
    fig.tight_layout()
    fig.savefig(path, dpi=100, format="png")  # path may be a temporary name without .png
    plt.close(fig)
