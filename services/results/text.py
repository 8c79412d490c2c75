"""report.txt and timing.txt: a run's report for people, from report.json's content."""

from __future__ import annotations

from pathlib import Path

from services.runtime.provenance import describe_code
from services.runtime.timing import Histogram


def pooled_histogram(loops, key) -> Histogram:
    h = Histogram()
    for lp in loops:
        d = lp.get(key) or {}
        for start_us, count in (d.get("bins") or {}).items():
            h.counts[int(start_us) * 1000 // h.bin_ns] += count
        h.overflow += d.get("overflow", 0)
    return h


def histograms_text(loops) -> str:
    """cyclictest-style histograms of the robot loop and its answers, all episodes pooled."""
    parts = []
    for key, title in (("lateness", "robot 1 kHz loop: wake-up lateness (us)"),
                       ("execution", "robot 1 kHz loop: execution time per cycle (us)"),
                       ("answer_latency", "FRI answer latency: measurement published -> command received (us)"),
                       ("closed_loop_latency", "closed loop: measurement -> sensor -> estimator -> commander -> "
                                               "robot (us)")):
        parts.append(pooled_histogram(loops, key).text(title))
    return "\n".join(parts)


def provenance_text(p: dict) -> str:
    """One line: the code, the date and the command line that made a run."""
    return f"made by etar-testbench {describe_code(p)} on {p.get('date')}: {p.get('command')}"


def served_text(e: dict) -> list[str]:
    """etar-bench serve's episode: what the lab's FRI remote did."""
    w = e.get("wire") or {}
    d = w.get("datagrams") or {}
    f = e.get("fri") or {}
    lines = ["", f"served over FRI 1.0/UDP: KRC {w.get('address', '?')} -> remote {w.get('remote', '?')}, "
                 f"KRL program {w.get('krl', '?')}; {e['sim_seconds']:.1f} s ({e['reason']})",
             f"  datagrams: {d.get('sent', 0)} measurements sent, {d.get('received', 0)} received, "
             f"{d.get('accepted', 0)} commands in time, {d.get('late', 0)} late, {d.get('duplicate', 0)} duplicate, "
             f"{d.get('wrong_size', 0)} wrong size, {d.get('wrong_id', 0)} wrong id, {d.get('invalid', 0)} invalid, "
             f"{d.get('foreign', 0)} from other senders (ignored)"
             + (f" (last: {w['last_reject_reason']})" if w.get("last_reject_reason") else ""),
             f"  command mode: {w.get('command_mode_s', 0.0):.2f} s, entered {f.get('command_mode_entered', 0)} "
             f"time(s), left {f.get('command_mode_left', 0)}; FRI missed {f.get('missed', 0)} cycle(s), longest run "
             f"{f.get('longest_miss_run', 0)}; final control mode {w.get('control_mode', '?')}",
             f"  peak contact force {e['peak_contact_force']:.1f} N; safety stop: "
             + (f"{w['safety_stop']['reason']} at {w['safety_stop']['at_s']:.2f} s" if w.get("safety_stop")
                else "none")]
    lines.append("  times from the served episode's first cycle (its recording begins with the settle before it)")
    for ref in w.get("first_command_refusals") or []:
        lines.append(f"  {ref['at_s']:7.2f} s  refused: {ref['reason']}")
    for ev in w.get("krl_events") or []:
        lines.append(f"  {ev['at_s']:7.2f} s  KRL {ev['kind']}: {ev['text']}")
    changes = w.get("states") or []
    if changes:
        lines.append("  link: " + ", ".join(f"{c['at_s']:.2f} s {c['state']}/{c['quality']}" for c in changes[:12])
                     + (f", ... ({len(changes)} changes)" if len(changes) > 12 else ""))
    return lines


def netft_text(r: dict) -> list[str]:
    """The Net F/T box's line: what it streamed, whom it refused, the garbage it was sent."""
    n = ((r.get("timing") or {}).get("services") or {}).get("ft_sensor", {}).get("netft")
    if not n:
        return []
    return ["", f"Net F/T box {n.get('address', '?')} (RDT {n.get('rdt_port', '?')}, HTTP {n.get('http_port', '-')}, "
                f"calibration {n.get('calibration_port', '-')}): {n.get('requests', 0)} RDT requests, "
                f"{n.get('records_sent', 0)} records sent; refused {n.get('refused', 0)} start(s) (four streams "
                f"running), ended {n.get('unreachable', 0)} stream(s) of clients gone, ignored "
                f"{n.get('ignored', 0)} malformed RDT datagram(s); HTTP {n.get('http_requests', 0)} page(s), "
                f"{n.get('http_refused', 0)} refused; calibration {n.get('calibration_requests', 0)}, "
                f"{n.get('calibration_refused', 0)} refused"]


def render_text(r: dict) -> str:
    """report.txt: the report ``r`` (report.json's content) for people."""
    lines = (_header(r) + _episodes(r) + _selection(r["learning"]["selection"]) + _reproductions(r)
             + _comparison(r) + _timing(r))
    return "\n".join(lines) + "\n"


def _header(r: dict) -> list[str]:
    """The run, where and by what it ran, and whatever went wrong with it."""
    lines = [f"ETAR testbench run {r['run_id']} - scenario {r['scenario']} ({r['source']})",
             f"clock {r['environment']['clock']}, transport {r.get('transport', '-')}"
             + (", FRI 1.0 and Net F/T over UDP" if r.get("wire") == "udp" else "") + ", SCHED_FIFO "
             f"{'yes' if r['environment']['sched_fifo'] else 'no'}, kernel {r['environment']['kernel']}, "
             f"{r['environment']['cpus']} CPUs, {r['wall_seconds']:.1f} s wall"]
    if r.get("provenance"):
        lines.append(provenance_text(r["provenance"]))
    prof = r["environment"].get("realtime_profile")
    if prof:
        fifo = {k: v["sched_fifo"] for k, v in r["environment"].get("services", {}).items() if v["sched_fifo"]}
        lines.append(f"realtime profile: asked {', '.join(prof['requested'])}; granted "
                     f"{', '.join(prof['granted']) or 'nothing'}"
                     + "".join(f"; {k} refused: {v}" for k, v in prof["refused"].items())
                     + (f"; SCHED_FIFO {', '.join(f'{k} {v}' for k, v in fifo.items())}" if fifo else ""))
    if r["error"]:
        lines.append(f"RUN FAILED: {r['error']}")
    for rs in r.get("restarts") or []:
        lines.append(f"service {rs['role']} lost {rs['lost_at_s']:.1f} s into the run (exit code {rs['exit_code']}), "
                     f"restarted by its policy, back after {rs['back_after_s']:.1f} s")
    for kind in ("demonstrations", "reproductions"):
        for i, e in enumerate(r[kind]):
            for g in e.get("recording_gaps") or []:
                if g["cycles_missing"] is None:
                    what = "the robot cycles between them are unknown"
                else:
                    what = (f"robot cycles {g['last_cycle'] + 1}..{g['next_first_cycle'] - 1} not recorded "
                            f"({g['cycles_missing']} cycles)")
                lines.append(f"{kind[:-1]} {i}: the recorder restarted; the recording goes on in "
                             f"{g['next_part']}: {what}")
    return lines


def _episodes(r: dict) -> list[str]:
    """The demonstrations, a served episode and the Net F/T box."""
    lines = ["", f"demonstrations: {len(r['demonstrations'])}"]
    for i, d in enumerate(r["demonstrations"]):
        lines.append(f"  {i:2d} {d['side']:>5}  {d['reason']:<13} {d['sim_seconds']:6.1f} s sim  "
                     f"{d['wall_seconds']:6.1f} s wall")
    for e in r.get("served") or []:
        lines += served_text(e)
    lines += netft_text(r)
    return lines


def _selection(sel: dict | None) -> list[str]:
    """How the number of phases was chosen."""
    if not sel:
        return []
    lines = [""]
    method = sel.get("method", "pooled")
    lines.append(f"phases chosen: {sel['best']} ({sel['criterion']}"
                 f"{', per demonstration' if method == 'per_demonstration' else ''})")
    for i, d in enumerate(sel.get("per_demonstration", [])):
        lines.append(f"  demo {i:2d}: " + "  ".join(
            f"K={k} {d['scores'][k]:.0f}{'*' if int(k) == d['best'] else ''}" for k in sorted(d["scores"], key=int))
            + f"  -> {d['best']}")
    if "votes" in sel:
        lines.append("  votes: " + ", ".join(f"{k} phases: {v}" for k, v in sel["votes"].items()))
    for k in sorted(sel.get("scores", {}), key=int):
        lines.append(f"  K={k}: score {sel['scores'][k]:.1f}, log-likelihood {sel['log_likelihoods'][k]:.1f}, "
                     f"{sel['n_parameters'][k]} parameters{'  <-' if int(k) == sel['best'] else ''}")
    return lines


def _reproductions(r: dict) -> list[str]:
    """Each reproduction's result and phase scores, and their totals."""
    s = r["summary"]
    if not r["reproductions"]:
        return []
    lines = ["", f"reproductions: {s['successes']} of {s['reproductions']} reached the goal with bounded force"]
    models = any(rp.get("model") for rp in r["reproductions"])
    lines.append("   #  side  " + ("model " if models else "") +
                 "result                 peak F [N]  phase acc  trans. err [s]  sim [s]  wall [s]")
    for rp in r["reproductions"]:
        ph = rp["phases"]
        acc = ph.get("accuracy")
        te = ph.get("mean_transition_error_s")
        lines.append(f"  {rp['index']:2d} {rp['side']:>5}  " + (f"{rp.get('model') or '-':<5} " if models else "")
                     + f"{rp['reason']:<22} {rp['peak_contact_force']:10.1f}  "
                     f"{'-' if acc is None else f'{acc:9.3f}'}  "
                     f"{'-' if te is None or te != te else f'{te:14.3f}'}  {rp['sim_seconds']:7.1f}  "
                     f"{rp['wall_seconds']:8.1f}")
    acc = s["online_phase_accuracy"]
    te = s["mean_transition_error_s"]
    lines.append(f"online phase accuracy overall: {'-' if acc is None else f'{acc:.4f}'}; mean transition "
                 f"error: {'-' if te is None else f'{te:.3f} s'}")
    held = gap = scored = 0
    for rp in r["reproductions"]:
        unconditioned = rp["phases"].get("unconditioned") or {}
        held, gap = held + unconditioned.get("arm_held", 0), gap + unconditioned.get("gap", 0)
        scored += rp["phases"].get("updates", 0)
    if held or gap:
        lines.append(f"estimates that did not condition on their step: arm held by the KRC {held}, "
                     f"sample missing {gap}, of {scored}")
    return lines


def _comparison(r: dict) -> list[str]:
    """ETAR against STAR, when the run learned both."""
    if not (r["learning"].get("offline") or r["summary"].get("by_model")):
        return []
    from services.results.compare import comparison_text

    return ["", *comparison_text(r)]


def _timing(r: dict) -> list[str]:
    """The robot loop, FRI per episode, the real-time factor, the closed loop and the links."""
    s = r["summary"]
    lines = []
    t = r["timing"]
    lockstep = r["environment"]["clock"] == "lockstep"
    host = "host " if lockstep else ""
    lines.append("")
    if lockstep:
        lines.append(f"timing (simulated): {t['robot_loop']['cycles']} FRI cycles of 1 ms in lockstep - each waits "
                     "for its answers, so every deadline is met by construction; the latencies below are the host's "
                     "wall clock running the simulation, not the system's timing")
    else:
        lines.append(f"robot loop: {t['robot_loop']['cycles']} cycles, {t['robot_loop']['deadline_misses']} deadline "
                     f"misses, longest run {t['robot_loop']['longest_miss_run']}")
    episodes = [("demonstration", i, d) for i, d in enumerate(r["demonstrations"])] + \
               [("reproduction", rp["index"], rp) for rp in r["reproductions"]]
    if any(e.get("fri") for _, _, e in episodes):
        lines.append("FRI per episode:        answered   missed     late  longest miss run  at PERFECT  drops from "
                     "PERFECT  CMD after [s]  CMD left/entered  duplicates")
        for kind, i, e in episodes:
            f, fq = e.get("fri") or {}, e.get("fri_quality") or {}
            if not f:
                continue
            if kind == "demonstration" and f["answered"] == 0:
                # the teacher guides the arm in gravity compensation: no commander
                # runs, so every cycle closes unanswered; that is not a link fault
                lines.append(f"  {kind:<13} {i:3d}  gravity compensation, nobody answers FRI "
                             f"({f['missed']} cycles unanswered, as expected)")
                continue
            span = sum((fq.get("seconds_at") or {}).values())
            at = (fq["seconds_at"]["PERFECT"] / span) if span else None
            cmd = fq.get("first_cmd_s")
            # the robot's clock runs over the whole run; the column is from the episode's start
            cmd = None if cmd is None else cmd - fq.get("start_s", 0.0)
            lines.append(f"  {kind:<13} {i:3d} {f['answered']:10d} {f['missed']:8d} {f['late']:8d} "
                         f"{f['longest_miss_run']:17d}  {'-' if at is None else f'{at:9.1%}'}  "
                         f"{fq.get('drops_from_perfect', 0):18d}  {'-' if cmd is None else round(cmd, 3):>13}"
                         f"  {f.get('command_mode_left', 0):7d}/{f.get('command_mode_entered', 0):<8d}"
                         f"  {f.get('duplicate', 0):10d}")
    rtf = s["real_time_factor"]
    lines.append(f"simulated {s['simulated_seconds']:.1f} s in {s['episode_wall_seconds']:.1f} s of episodes: "
                 f"{'-' if rtf is None else f'{rtf:.2f}'} x real time")
    cl = t.get("closed_loop", {})
    if cl.get("p99_us_max") is not None:
        lines.append(f"{host}closed loop (measurement -> sensor -> estimator -> commander -> robot): worst p99 "
                     f"{cl['p99_us_max']:.0f} us over {len(cl['per_episode'])} reproduction(s)")
    lines += link_lines(t, host)
    return lines


def link_lines(t: dict, host: str = "") -> list[str]:
    """The links' tables of report.json's ``timing``: each link at its receiver, and publish
    -> recorder; ``host``: "host " where the latencies are the host's running a lockstep run."""
    lines = []
    if t.get("links_received"):
        lines.append(f"{(host or 'link ') + 'latency at the receiver (us):':<54}p50      p99    p99.9      max   lost"
                     "  out-of-order  garbage  off-clock")
        for name, v in sorted(t["links_received"].items()):
            lat, off = v.get("latency", {}), v.get("off_clock", 0)
            if not lat.get("count") and not off:
                continue
            figures = (f"{lat['p50_us']:8.0f} {lat['p99_us']:8.0f} {lat['p99_9_us']:8.0f} {lat['max_us']:8.0f}"
                       if lat.get("count") else f"{'-':>8} {'-':>8} {'-':>8} {'-':>8}")
            lines.append(f"  {name:<45} {figures} {v['lost']:6d} {v['out_of_order']:13d} {v['bad']:8d} {off:10d}")
    lines.append(f"{(host or 'link ') + 'latency, publish -> recorder (us):':<42}p50      p99      max   lost  out-of-order"
                 "  off-clock")
    for topic, v in sorted(t["links_publish_to_recorder"].items()):
        figures = (f"{v['p50_us']:9.0f} {v['p99_us']:8.0f} {v['max_us']:8.0f}" if "p50_us" in v
                   else f"{'-':>9} {'-':>8} {'-':>8}")
        lines.append(f"  {topic:<22} {figures} {v['lost']:6d} {v['out_of_order']:6d} {v.get('off_clock', 0):10d}")
    if any(v.get("off_clock") for v in [*t.get("links_received", {}).values(), *t["links_publish_to_recorder"].values()]):
        lines.append("  off-clock: messages whose publish stamp is not on the receiver's clock (negative, or over "
                     "60 s: a foreign peer's, a paused process); not among the latencies")
    return lines


def summary_line(report: dict, out, page: bool = True) -> str:
    """One line: phases chosen, reproductions that reached the goal, online accuracy,
    where the report is (report.html, with its figures, when it was written); or that
    the run failed, and why."""
    s = report["summary"]
    parts = []
    if s.get("phases_chosen") is not None:
        parts.append(f"{s['phases_chosen']} phases")
    if s.get("reproductions"):
        parts.append(f"{s['successes']} of {s['reproductions']} reproductions reached the goal")
        acc = s.get("online_phase_accuracy")
        parts.append(f"online phase accuracy {acc:.4f}" if acc is not None else "no online phase estimate")
    html = Path(out) / "report.html"
    where = f"report {html if page and html.is_file() else Path(out) / 'report.txt'}"
    if report["error"] is not None:
        return f"{report['scenario']}: RUN FAILED ({report['error']}); " + "; ".join(parts + [f"partial {where}"])
    return f"{report['scenario']}: " + "; ".join(parts + [where])
