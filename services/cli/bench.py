"""``etar-bench``: run scenarios and read their reports.

    etar-bench run SCENARIO [--out DIR] [--clock realtime|lockstep] [--transport zenoh|inproc] [--foxglove [PORT]]
    etar-bench check SCENARIO
    etar-bench serve SCENARIO --out DIR [--fri-remote HOST:PORT] [--krl frilibrary|lwr_hw] [--netft HOST]
                     [--start X,Y,Z] [--max-seconds S]
    etar-bench demo [--world valley|hose_coupler] [--side left|right] [--png FILE] [--npz FILE]
    etar-bench sweep SCENARIO --param PATH=V1,V2,... [--repeats N] --out DIR [--cluster ADDRESS]
    etar-bench report RUN_DIR [--json]
    etar-bench info PATH [--json]
    etar-bench diff RUN_A RUN_B [--json]
    etar-bench recover FILE... [--out FILE]
    etar-bench figures RUN_DIR
    etar-bench compare RUN_DIR [--seeds N] [--pair I,J]
    etar-bench export RUN_DIR --foxglove [--visual-rate-hz HZ]
    etar-bench certs DIR [--host IP]
    etar-bench router [--listen tcp/0.0.0.0:7447]
"""

from __future__ import annotations

import argparse
import json
import shlex
import signal
import sys
import time
from pathlib import Path

import numpy as np

from robot_sim.worlds import TASK_WORLDS
from services.cli.version import add_version_argument
from services.cli.parsing import OneLineErrorParser
from services.cli.zenoh_flags import add_zenoh_arguments, zenoh_options
from services.transport.session import ZENOH_PORT
from services.runtime.visual_topics import FOXGLOVE_PORT, VISUAL_RATE_HZ, check_visual_rate


def _profile(text: str) -> str:
    from services.run.realtime_profile import parse_profile

    try:
        parse_profile(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def cmd_run(args) -> int:
    from etar.task import TaskError
    from services.run.options import RunOptions
    from services.run.runner import Runner
    from services.scenario import ScenarioError, load_scenario
    from services.transport.credentials import CredentialsError
    from services.runtime.files import FileWriteError
    from services.transport.hosts import HostsError

    out = args.out or f"runs/{Path(args.scenario).stem}-{time.strftime('%Y%m%d-%H%M%S')}"
    try:
        scenario = load_scenario(args.scenario)
        if args.clock:
            scenario = scenario.replace("clock", args.clock)
        options = RunOptions(out=out, run_id=args.run_id, zenoh=zenoh_options(args) if args.connect else None,
                             transport=args.transport, attach=args.attach, ready_timeout=args.ready_timeout,
                             sched_fifo=args.sched_fifo_ends, realtime_profile=args.realtime_profile, tls=args.tls,
                             hosts=args.hosts, figures=not args.no_figures, foxglove=args.foxglove,
                             replace=args.replace, command=args.command_line, wire=args.wire)
        runner = Runner(scenario, options, progress=_say)
    except (ScenarioError, TaskError, CredentialsError, HostsError, ValueError) as exc:
        # every option refused before anything started (services.run.options)
        _say(f"etar-bench run: error: {exc}")
        return 2
    # SIGTERM (kill, docker stop) takes the same way out as Ctrl-C: the runner stops the
    # services it started and writes what it has; otherwise they outlive it as orphans
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        report = runner.run()
    except FileWriteError as exc:  # a full disk, a folder made read-only: what was kept stays readable
        _say(f"etar-bench run: failed: {exc}; what was kept is in {out} (etar-bench info {out})")
        return 1
    except KeyboardInterrupt as exc:
        written = (Path(out) / "report.json").exists()
        _say(f"etar-bench run: interrupted ({str(exc) or 'SIGINT'}); services stopped; "
             + (f"partial report in {out}" if written else "no report was written"))
        return 130
    print((Path(out) / "report.txt").read_text())
    _say(f"report: {out}/report.json, {out}/report.txt; recordings in {out}/recordings")
    # the last line, for a newcomer: what came out and where to read more
    print(summary_line(report, out, page=not args.no_figures), flush=True)
    return 0 if report["error"] is None else 1


def _xyz(text: str) -> tuple:
    parts = text.split(",")
    try:
        values = tuple(float(v) for v in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z in m, e.g. 0.5,0.0,0.3; got {text!r}")
    return values


def cmd_serve(args) -> int:
    """The simulated cell alone, for a lab's own FRI remote and Net F/T client."""
    from services.run.options import RunOptions
    from services.run.runner import Runner
    from services.run.serve import ServeOptions
    from services.scenario import ScenarioError, load_scenario

    try:
        scenario = load_scenario(args.scenario).replace("clock", "realtime")
        ports = ()
        for flag, value in (("--netft-rdt-port", args.netft_rdt_port), ("--netft-http-port", args.netft_http_port),
                            ("--netft-calibration-port", args.netft_calibration_port)):
            if value is not None:
                ports += (flag, str(value))
        serve = ServeOptions(fri_remote=args.fri_remote, fri_bind=args.fri_bind, krl=args.krl,
                             netft=None if args.netft == "none" else args.netft, netft_ports=ports,
                             start=args.start, max_seconds=args.max_seconds, fri_cycle_ms=args.fri_cycle_ms)
        options = RunOptions(out=args.out, run_id=args.run_id, realtime_profile=args.realtime_profile,
                             figures=False, replace=args.replace, command=args.command_line, serve=serve,
                             robot_args=tuple(args.robot_flag or ()))
        runner = Runner(scenario, options, progress=_say)
    except (ScenarioError, ValueError) as exc:
        _say(f"etar-bench serve: error: {exc}")
        return 2
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        report = runner.run()
    except KeyboardInterrupt:
        written = (Path(args.out) / "report.json").exists()
        _say("etar-bench serve: interrupted; services stopped; "
             + (f"report in {args.out}" if written else "no report was written"))
        return 130
    print((Path(args.out) / "report.txt").read_text(), flush=True)
    _say(f"report: {args.out}/report.json, {args.out}/report.txt; recording in {args.out}/recordings")
    return 0 if report["error"] is None else 1


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


def cmd_check(args) -> int:
    """Validate a scenario as the runner would before it starts anything, and print it with
    every default filled in (what `etar-bench run` would run)."""
    from etar.task import TaskError
    from services.run.preflight import EPISODE_NAMES, preflight
    from services.scenario import ScenarioError, load_scenario

    try:
        scenario = load_scenario(args.scenario)
        found = preflight(scenario)
    except (ScenarioError, TaskError) as exc:
        _say(f"etar-bench check: error: {exc}")
        return 2
    print(scenario.to_yaml(), end="", flush=True)
    kinds = {}
    for _, kind, _, _, _ in found.starts:
        kinds[EPISODE_NAMES[kind]] = kinds.get(EPISODE_NAMES[kind], 0) + 1
    episodes = ", ".join(f"{n} {kind}{'s' if n > 1 else ''}" for kind, n in kinds.items()) or "no episodes"
    model = f"; model {scenario.model_path()} loads ({found.model.n_phases} phases)" if found.model else ""
    _say(f"{args.scenario}: valid: {episodes}, every start within the arm's reach{model}")
    return 0


def cmd_demo(args) -> int:
    """One demonstration by the teacher, run by the nodes in one process; its recording,
    and on request a picture and the arrays ``etar learn`` reads."""
    from robot_sim.labels import LABELERS
    from services.recordings.demonstrations import load_demonstration
    from services.recordings.format import RecordingError
    from services.run.demonstration import demonstration_scenario, record_demonstration
    from services.scenario import ScenarioError

    out = args.out or f"runs/demo-{args.world}-{time.strftime('%Y%m%d-%H%M%S')}"
    for flag, path in (("--png", args.png), ("--npz", args.npz)):
        if path is not None and not Path(path).expanduser().resolve().parent.is_dir():
            _say(f"etar-bench demo: error: {flag} {path}: the folder {Path(path).parent} does not exist")
            return 2
    try:
        scenario = demonstration_scenario(args.world, side=args.side, seed=args.seed, spread=args.spread,
                                          max_seconds=args.max_seconds)
    except ScenarioError as exc:
        field = exc.path.rsplit(".", 1)[-1]
        flag = {"sides": "--side", "start_spread": "--spread", "start": "--spread", "goal_x": "--spread",
                "max_seconds": "--max-seconds"}.get(field, f"--{field}")
        _say(f"etar-bench demo: error: {flag}: {exc.problem}" + (f", got {exc.value!r}" if exc.has_value else ""))
        return 2
    try:
        report, recording = record_demonstration(scenario, out, progress=_say, replace=args.replace)
    except ValueError as exc:  # the run folder: a file, or one that holds a run
        _say(f"etar-bench demo: error: {exc}")
        return 2
    if report["error"] is not None:
        _say(f"etar-bench demo: the demonstration failed: {report['error']} (run folder {out})")
        return 1
    (d,) = report["demonstrations"]
    try:
        demo = load_demonstration(recording)
    except RecordingError as exc:  # e.g. too short to give two samples
        _say(f"etar-bench demo: the demonstration ended {d['reason']} after {d['sim_seconds']:.3f} s simulated and "
             f"gives no demonstration to learn from: {exc}")
        return 1
    counts = np.bincount(demo["phases"]).tolist()
    _say(f"{args.world} demonstration ({args.side}): {d['reason']} after {d['sim_seconds']:.2f} s simulated, "
         f"{len(demo['states'])} samples at {1 / demo['dt']:.0f} Hz, steps per true phase {counts}; "
         f"recording {recording}")
    if args.png:
        from services.results.figures import demonstration_figure

        demonstration_figure(demo, Path(args.png), f"{args.world} demonstration (seed {args.seed})",
                             LABELERS[args.world].names)
        _say(f"wrote {args.png}")
    if args.npz:
        np.savez(args.npz, states=demo["states"], forces=demo["forces"], phases=demo["phases"],
                 dt=np.float64(demo["dt"]), t=demo["t"])
        _say(f"wrote {args.npz} (etar learn {args.npz} ... reads it)")
    return 0 if d["reason"] == "teacher_done" else 1


def cmd_sweep(args) -> int:
    from etar.task import TaskError
    from services.run.sweep import Parameter, SweepError, SweepInterrupted, sweep
    from services.scenario import ScenarioError, load_scenario

    signal.signal(signal.SIGTERM, _interrupt)  # kill: the same way out as Ctrl-C
    try:
        params = [Parameter.parse(p) for p in args.param]
        result = sweep(load_scenario(args.scenario), params, repeats=args.repeats, out=args.out, record=args.record,
                       workers=args.workers, cluster=args.cluster, learn_threads=args.learn_threads,
                       replace=args.replace, say=_say)
    except (SweepError, ScenarioError, TaskError) as exc:
        _say(f"etar-bench sweep: error: {exc}")
        return 2
    except SweepInterrupted as stop:
        s = stop.summary or {}
        _say(f"etar-bench sweep: interrupted ({stop.why}): {s.get('runs', 0)} run(s) finished"
             + (f", their table {s['table']} (sweep.json marked incomplete)" if s.get("table") else ", no table")
             + f"; {len(s.get('interrupted_runs', []))} interrupted (their partial reports under {args.out}/runs), "
             f"{len(s.get('not_started', []))} not started")
        return 130
    except KeyboardInterrupt as exc:  # before any run started
        _say(f"etar-bench sweep: interrupted ({str(exc) or 'SIGINT'}) before any run started")
        return 130
    where = result["cluster"] or f"{result['workers']} local processes"
    print(f"sweep: {result['runs']} runs ({result['failed']} failed) in {result['wall_seconds']:.0f} s on {where}; "
          f"table {result['table']}; plots {', '.join(result['plots']) or 'none'}", flush=True)
    return 0 if result["failed"] == 0 else 1


def _interrupt(signum, frame):
    raise KeyboardInterrupt(signal.Signals(signum).name)


def cmd_report(args) -> int:
    from services.results.folder import RunFolderError, read_report

    path = Path(args.run_dir)
    for name in ("report.txt", "report.json"):
        if not (path / name).exists():
            _say(f"etar-bench report: {path / name} not found (is {path} a run directory?)")
            return 2
    try:
        report = read_report(path)
    except RunFolderError as exc:
        _say(f"etar-bench report: {exc}")
        return 2
    if args.json:
        print(json.dumps(report, indent=1, allow_nan=False))
    else:
        print((path / "report.txt").read_text(), end="")
    if report.get("error"):
        _say(f"etar-bench report: the run failed: {report['error']}")
        return 1
    return 0


def cmd_info(args) -> int:
    """What a recording or a run holds, as ``mcap info`` / ``ros2 bag info`` would say it."""
    from services.results.info import describe, info_text

    try:
        described = describe(args.path)
    except ValueError as exc:  # InfoError, RecordingError: one line naming the file
        _say(f"etar-bench info: error: {exc}")
        return 2
    print(json.dumps(described, indent=1, allow_nan=False) if args.json else info_text(described), flush=True)
    return 0


def cmd_diff(args) -> int:
    """Like diff: 0 when the two runs recorded the same content and results, 1 when not,
    2 on trouble."""
    from services.results.diff import diff_runs

    try:
        result = diff_runs(args.run_a, args.run_b)
    except ValueError as exc:  # DiffError, RecordingError
        _say(f"etar-bench diff: error: {exc}")
        return 2
    print(json.dumps(result.to_dict(), indent=1, allow_nan=False) if args.json else result.text(), flush=True)
    return 0 if result.same else 1


def cmd_recover(args) -> int:
    from services.recordings.format import RecordingError
    from services.recordings.recovery import recover

    if args.out is not None and len(args.files) > 1:
        _say("etar-bench recover: --out names one output file: give one FILE with it")
        return 2
    missing = [f for f in args.files if not Path(f).is_file()]
    if missing:
        what = "a folder, not a recording" if Path(missing[0]).is_dir() else "no such file"
        _say(f"etar-bench recover: error: {missing[0]}: {what}")
        return 2
    if args.out is not None:  # refused before anything is read or written
        out = Path(args.out)
        problem = ("a folder; --out names the output file" if out.is_dir() else
                   f"its folder {out.parent} does not exist" if not out.parent.is_dir() else
                   "exists (pass --force to replace it)" if out.exists() and not args.force else None)
        if problem:
            _say(f"etar-bench recover: error: --out {args.out}: {problem}")
            return 2
    failed = 0
    for f in args.files:
        try:
            result = recover(f, args.out, overwrite=args.force)
        except RecordingError as exc:
            _say(f"etar-bench recover: error: {exc}")
            failed += 1
            continue
        except OSError as exc:  # the output's folder not writable, a full disk
            _say(f"etar-bench recover: error: {f}: could not write {exc.filename or args.out}: {exc.strerror}")
            failed += 1
            continue
        print(result.describe(), flush=True)
    return 1 if failed else 0


def cmd_figures(args) -> int:
    from services.results.figures import FiguresError, read_run_report
    from services.results.html import write_figures_and_page

    run_dir = Path(args.run_dir)
    try:
        read_run_report(run_dir)  # a run's folder, with a report to draw from
    except FiguresError as exc:
        _say(f"etar-bench figures: error: {exc}")
        return 2
    print(write_figures_and_page(run_dir, progress=_say), flush=True)
    problems = [run_dir / name for name in ("figures.error", "report.html.error") if (run_dir / name).is_file()]
    for path in problems:
        _say(f"etar-bench figures: {path}: {path.read_text().strip()}")
    return 1 if problems else 0


def cmd_export(args) -> int:
    from services.foxglove.export import export_foxglove
    from services.recordings.format import RecordingError

    if not args.foxglove:
        _say("etar-bench export: error: say what to add: --foxglove (the only export so far)")
        return 2
    try:
        check_visual_rate(args.visual_rate_hz, "--visual-rate-hz")
    except ValueError as exc:
        _say(f"etar-bench export: error: {exc}")
        return 2
    if not (Path(args.run_dir) / "recordings").is_dir():
        _say(f"etar-bench export: error: {args.run_dir}: no recordings/ folder: not a run's folder")
        return 2
    try:
        results = export_foxglove(args.run_dir, args.visual_rate_hz, progress=print)
    except RecordingError as exc:
        _say(f"etar-bench export: error: {exc}")
        return 1
    added = sum(1 for r in results if r.added)
    _say(f"etar-bench export: visual topics added to {added} of {len(results)} recording(s)")
    return 0


def cmd_compare(args) -> int:
    from services.results.compare import compare_run
    from services.results.figures import FiguresError

    if args.seeds < 1:
        _say(f"etar-bench compare: error: --seeds must be >= 1, got {args.seeds}")
        return 2
    try:
        pair = tuple(int(x) for x in args.pair.split(","))
        if len(pair) != 2:
            raise ValueError
    except ValueError:
        _say(f"etar-bench compare: error: --pair expects two demonstration numbers I,J (e.g. 0,1), got {args.pair!r}")
        return 2
    try:
        compare_run(args.run_dir, seeds=tuple(range(args.seeds)), progress=_say, pair=pair)
    except FiguresError as exc:
        _say(f"etar-bench compare: error: {exc}")
        return 2
    print((Path(args.run_dir) / "comparison.txt").read_text(), end="", flush=True)
    return 0


def cmd_certs(args) -> int:
    from services.runtime.roles import CREDENTIAL_NAMES as ROLES
    from services.transport.credentials import CredentialsError, make_credentials

    try:
        out = make_credentials(args.dir, hosts=tuple(args.host or ["127.0.0.1"]), roles=ROLES + tuple(args.role))
    except CredentialsError as exc:
        _say(f"etar-bench certs: error: {exc}")
        return 2
    print(f"{out}: ca.pem (ca.key signs: keep it off the hosts), router.pem/.key, and a certificate per role "
          f"({', '.join(ROLES + tuple(args.role))}); use with: etar-bench run SCENARIO --tls {out}", flush=True)
    return 0


def cmd_router(args) -> int:
    """A real Zenoh router (the Python library in router mode) for multi-host or container runs."""
    import zenoh

    from services.transport.session import ZenohOptions

    from services.transport.session import zenoh_reason

    opts = ZenohOptions(mode="router", connect=(), listen=tuple(args.listen or [f"tcp/0.0.0.0:{ZENOH_PORT}"]))
    try:
        conf = opts.config()
        session = zenoh.open(conf)
    except ValueError as exc:  # names the flag and the value
        _say(f"etar-bench router: error: {exc}")
        return 2
    except zenoh.ZError as exc:  # e.g. an address it cannot listen on
        _say(f"etar-bench router: error: --listen {' '.join(opts.listen)}: {zenoh_reason(exc)}")
        return 2
    with session:
        _say(f"zenoh router listening on {', '.join(opts.listen)}; Ctrl-C to stop")
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            return 0


def build_parser() -> OneLineErrorParser:
    from services.foxglove import export
    from services.recordings import recovery
    from services.results import diff
    from services.run import demonstration, sweep
    from services.scenario.checks import SIDES
    from services.run.options import WIRES, RunOptions
    from services.runtime.cycle import CLOCKS
    from services.runtime.roles import FIFO_CHAIN
    from services.transport.cell import TRANSPORTS

    from robot_sim.krl import LAB_CONVENTIONS
    from services.run.serve import ServeOptions

    fifo = ", ".join(f"{role} {priority}" for role, priority in FIFO_CHAIN)
    fifo_ends = " and ".join(f"{role} ({priority})" for role, priority in RunOptions.fifo_priorities)
    parser = OneLineErrorParser(prog="etar-bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_version_argument(parser, "etar-bench")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="run a scenario: demonstrate, learn, reproduce, report")
    p.add_argument("scenario", help="scenario YAML file (see docs/scenarios.md)")
    p.add_argument("--out", metavar="DIR",
                   help="the run's folder, created (default runs/<scenario>-<time>); one that holds a run is "
                        "refused unless --replace")
    p.add_argument("--replace", action="store_true",
                   help="--out holds an earlier run: remove it first (its report, recordings, model, figures)")
    p.add_argument("--clock", choices=CLOCKS, help="override the scenario's clock")
    p.add_argument("--run-id", help="run id (default <scenario>-<random>)")
    p.add_argument("--transport", choices=TRANSPORTS, default=RunOptions.transport,
                   help="zenoh: every role in its own process over Zenoh (the lab's layout, realtime or lockstep; "
                        "default); inproc: every role in this process on an in-memory bus (lockstep only, "
                        "several times faster, the same recordings)")
    p.add_argument("--attach", action="store_true",
                   help="drive services that are already running (docker-compose) instead of starting them")
    p.add_argument("--ready-timeout", type=float, default=RunOptions.ready_timeout,
                   help="seconds to wait for the services")
    p.add_argument("--realtime-profile", default="auto", type=_profile, metavar="auto|none|PARTS",
                   help="with --clock realtime, what the run asks of the machine, each where permitted: fifo "
                        f"(SCHED_FIFO for the FRI chain: {fifo}), isolate (the robot alone on the last CPU), "
                        "poll (idle CPUs poll: "
                        "/dev/cpu_dma_latency 0). auto (default): all three; none; or a comma list. The report "
                        "says what was granted")
    p.add_argument("--sched-fifo-ends", action="store_true",
                   help=f"SCHED_FIFO (where permitted) for {fifo_ends} only, whatever the profile (the "
                        "profile's fifo covers the whole chain)")
    p.add_argument("--tls", metavar="DIR",
                   help="the run's credentials (etar-bench certs DIR): the runner is the run's Zenoh router, which "
                        "takes mutual TLS only and lets only the run's roles publish or read")
    p.add_argument("--hosts", metavar="ROLES:ROLES:...",
                   help="the services on hosts of this machine, each a network namespace with its own address "
                        "(root and iproute2 needed), roles by host, e.g. robot,ft_sensor:phase_estimator,"
                        "impedance_commander:recorder,teacher; the runner is the run's Zenoh router")
    p.add_argument("--foxglove", nargs="?", const=FOXGLOVE_PORT, type=int, metavar="PORT",
                   help="watch the run live in Foxglove: the arm, the world, the wrench, the stiffness and the phase "
                        f"over Foxglove's WebSocket protocol on PORT (default {FOXGLOVE_PORT}; 0: any free port, "
                        "printed); "
                        "connect Foxglove to ws://localhost:PORT")
    p.add_argument("--wire", choices=WIRES, default=RunOptions.wire,
                   help="zenoh (default): the nodes talk over Zenoh; udp: over the lab's protocols, the KRC and "
                        "the commander FRI 1.0 over UDP, the estimator reading the sensor's Net F/T box (realtime "
                        "only; docs/fri.md)")
    p.add_argument("--no-figures", action="store_true",
                   help="skip the thesis' figures and report.html after the report (etar-bench figures RUN_DIR "
                        "draws both later)")
    add_zenoh_arguments(p, process_flags=False)  # the services get theirs from the run
    p.set_defaults(func=cmd_run)
    p = sub.add_parser("serve", help="the simulated cell alone (arm, KRC, sensor, recorder) on the realtime clock, "
                                     "for a lab's own FRI 1.0 remote over UDP and Net F/T client (docs/fri.md)")
    p.add_argument("scenario", help="scenario YAML file: its world, seed and cell (and the start of its first "
                                    "reproduction, where the arm is held)")
    p.add_argument("--out", metavar="DIR", required=True,
                   help="the folder for the recording and the report (one that holds a run is refused unless "
                        "--replace)")
    p.add_argument("--replace", action="store_true", help="--out holds an earlier run: remove it first")
    p.add_argument("--fri-remote", default=ServeOptions.fri_remote, metavar="HOST:PORT",
                   help=f"where the KRC sends its measurement datagrams: the remote's address (default "
                        f"{ServeOptions.fri_remote}, the port both public FRI 1.0 remote libraries listen on)")
    p.add_argument("--fri-bind", default=ServeOptions.fri_bind, metavar="HOST:PORT",
                   help="the KRC's own address (default: loopback, any free port; the remote answers to it)")
    p.add_argument("--krl", choices=LAB_CONVENTIONS, default=ServeOptions.krl,
                   help="the KRL program's start/stop convention: frilibrary (the Stanford FRI Library's "
                        "FRIControl.src, default) or lwr_hw (CentroEPiaggio's ros_control.src)")
    p.add_argument("--fri-cycle-ms", type=int, default=ServeOptions.fri_cycle_ms, metavar="MS",
                   help="the FRI cycle, as KRL's friOpen(MS) sets it: 1..100 ms (default 1); the KRC's control "
                        "runs every 1 ms physics step all the same")
    p.add_argument("--netft", default=ServeOptions.netft, metavar="HOST",
                   help="the Net F/T box's IPv4 address (default 127.0.0.1; 'none': no box); RDT on UDP 49152, "
                        "HTTP on 80, calibration on TCP 49151 unless the flags below say otherwise")
    p.add_argument("--netft-rdt-port", type=int, metavar="PORT", help="the box's RDT UDP port (0: any free one)")
    p.add_argument("--netft-http-port", type=int, metavar="PORT", help="the box's HTTP port (0: any free one)")
    p.add_argument("--netft-calibration-port", type=int, metavar="PORT",
                   help="the box's TCP calibration port (0: any free one)")
    p.add_argument("--start", type=_xyz, metavar="X,Y,Z",
                   help="where the tcp is held, m, tool pointing down (default: the scenario's first reproduction "
                        "start, unperturbed)")
    p.add_argument("--max-seconds", type=float, default=ServeOptions.max_seconds, metavar="S",
                   help=f"how long to serve (default {ServeOptions.max_seconds:g} s; Ctrl-C ends it sooner, with "
                        "the report)")
    p.add_argument("--run-id", help="run id (default <scenario>-<random>)")
    p.add_argument("--realtime-profile", default="auto", type=_profile, metavar="auto|none|PARTS",
                   help="what the run asks of the machine (as etar-bench run)")
    p.add_argument("--robot-flag", action="append", metavar="FLAG",
                   help="a further flag for the robot, e.g. --robot-flag=--fri-packet-loss=0.01 (repeatable): the "
                        "link's faults apply to the UDP link too")
    p.set_defaults(func=cmd_serve)
    p = sub.add_parser("check", help="validate a scenario without running it (the model file, every start) and "
                                     "print it with every default filled in")
    p.add_argument("scenario", help="scenario YAML file (see docs/scenarios.md)")
    p.set_defaults(func=cmd_check)
    p = sub.add_parser("demo", help="one demonstration by the simulated teacher, in one process: its recording, "
                                    "and on request a picture and the arrays etar learn reads")
    p.add_argument("--world", choices=TASK_WORLDS, default="valley", help="the task world")
    p.add_argument("--side", choices=SIDES, default=SIDES[0], help=f"valley: starting side (default {SIDES[0]})")
    p.add_argument("--seed", type=int, default=0, help="the scenario's seed (default 0)")
    p.add_argument("--spread", type=float, default=0.0, help="random start offset per axis, m (default 0)")
    p.add_argument("--max-seconds", type=float, default=demonstration.MAX_SECONDS,
                   help=f"simulated-time limit (default {demonstration.MAX_SECONDS:g})")
    p.add_argument("--out", metavar="DIR", help="run folder for the recording, created (default "
                                                "runs/demo-<world>-<time>); one that holds a run is refused unless "
                                                "--replace")
    p.add_argument("--replace", action="store_true", help="--out holds an earlier run: remove it first")
    p.add_argument("--png", metavar="FILE", help="write a picture of the demonstration to this file (its folder must "
                                                 "exist)")
    p.add_argument("--npz", metavar="FILE", help="write its arrays to this file (states, forces, phases, dt: what etar "
                                                 "learn reads)")
    p.set_defaults(func=cmd_demo)
    p = sub.add_parser("sweep", help="run every combination of scenario parameters x seeds in parallel, "
                                     "in-process; a table and plots",
                       description=sweep.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenario", help="scenario YAML file (see docs/scenarios.md)")
    p.add_argument("--param", action="append", default=[], metavar="PATH=V1,V2,...",
                   help="a scenario parameter and its values, e.g. cell.sensor_noise=0.5,1,2 or "
                        "reproduce.start_perturbation=0.01,0.03 (repeatable: every combination runs)")
    p.add_argument("--repeats", type=int, default=1, help="seeds per combination: the scenario's seed + 0..N-1")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="the sweep's folder, created, for the table, the plots and the runs; one that holds a sweep "
                        "is refused unless --replace")
    p.add_argument("--replace", action="store_true", help="--out holds an earlier sweep: remove it first")
    p.add_argument("--record", choices=sweep.RECORD, default="summary",
                   help="what to keep of each run: everything (recordings with Foxglove's visual topics), its "
                        "report and model (default), or nothing")
    p.add_argument("--workers", type=int, help="local processes (default: the CPUs this process may use)")
    p.add_argument("--cluster", metavar="ADDRESS",
                   help="a Dask scheduler, e.g. tcp://10.0.0.5:8786, to send the runs to instead")
    p.add_argument("--learn-threads", type=int,
                   help="numba threads per run's learner (default: the CPUs divided among the workers)")
    p.set_defaults(func=cmd_sweep)
    p = sub.add_parser("report", help="print the report of a finished run")
    p.add_argument("run_dir")
    p.add_argument("--json", action="store_true", help="print report.json instead of the text")
    p.set_defaults(func=cmd_report)
    p = sub.add_parser("info", help="what a recording or a run holds: topics with schema, counts, rates, duration, "
                                    "gaps, episodes and their results, the scenario and the code that made it")
    p.add_argument("path", help="a recording (.mcap) or a run's folder")
    p.add_argument("--json", action="store_true", help="print it as JSON (for scripts)")
    p.set_defaults(func=cmd_info)
    p = sub.add_parser("diff", help="two runs compared: results side by side, and the recorded content as the "
                                    "equivalence tests compare it; exit 0 same, 1 different, 2 trouble",
                       description="Compare two runs' results and recorded content; name the first message that "
                                   "differs. Exit code 0: the same; 1: different; 2: trouble.\n\n" + diff.IGNORED_TEXT,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_a", metavar="RUN_A", help="a run's folder")
    p.add_argument("run_b", metavar="RUN_B", help="another run's folder")
    p.add_argument("--json", action="store_true", help="print the comparison as JSON (for scripts)")
    p.set_defaults(func=cmd_diff)
    p = sub.add_parser("recover", help="make a truncated recording (a recorder killed mid-episode) a finished "
                                       "MCAP file with every complete chunk; the original is kept",
                       description=recovery.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("files", nargs="+", metavar="FILE", help="truncated .mcap recording(s)")
    p.add_argument("--out", help="output file (one FILE only; default FILE's name + .recovered.mcap beside it)")
    p.add_argument("--force", action="store_true", help="replace the output file if it exists")
    p.set_defaults(func=cmd_recover)
    p = sub.add_parser("figures", help="draw the thesis' figures (section 6) from a finished run into "
                                       "RUN_DIR/figures/ and rebuild RUN_DIR/report.html (every run does both unless "
                                       "--no-figures)")
    p.add_argument("run_dir", help="a finished run's folder (report.json, model.json, recordings/)")
    p.set_defaults(func=cmd_figures)

    p = sub.add_parser("export", help="add Foxglove's visual topics (the arm, the world, wrench, stiffness, "
                                      "phase) to a run's recordings made without them",
                       description=export.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir", help="a finished run's folder (recordings/*.mcap)")
    p.add_argument("--foxglove", action="store_true", help="the visual topics for Foxglove (required)")
    p.add_argument("--visual-rate-hz", type=float, default=VISUAL_RATE_HZ, metavar="HZ",
                   help=f"visual frames per second of simulated time (default {VISUAL_RATE_HZ:g})")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("compare", help="ETAR against STAR (thesis 6.3) on a finished run's demonstrations: both "
                                       "transition models fitted over several seeds, scored against the true "
                                       "phases; and Table C1's check: two demonstrations learned separately, "
                                       "their parameters compared")
    p.add_argument("run_dir", help="a finished run's folder with demonstrations and a learned model")
    p.add_argument("--seeds", type=int, default=3, help="seeds per transition model (default 3)")
    p.add_argument("--pair", default="0,1", metavar="I,J",
                   help="the two demonstrations of Table C1's check, learned separately and compared (default 0,1)")
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser("certs", help="make a run's credentials for mutual TLS (openssl): a CA of the run's own, "
                                     "a router certificate, one per role")
    p.add_argument("dir", help="folder for the certificates (an existing CA there is kept and signs the new ones)")
    p.add_argument("--host", action="append", metavar="IP",
                   help="an address the router listens on (repeatable; default 127.0.0.1)")
    p.add_argument("--role", action="append", default=[], metavar="NAME",
                   help="a further certificate beside the run's roles (repeatable)")
    p.set_defaults(func=cmd_certs)

    p = sub.add_parser("router", help="run a Zenoh router (for docker-compose or several hosts)")
    p.add_argument("--listen", action="append", help=f"endpoint(s), default tcp/0.0.0.0:{ZENOH_PORT}")
    p.set_defaults(func=cmd_router)
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.command_line = shlex.join(["etar-bench", *argv])  # what the report says made the run
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
