"""``etar-bench`` run, serve, check, demo and sweep: what each subcommand does once its
command line is parsed (``services.cli.bench``)."""

from __future__ import annotations

import argparse
import signal
import time
from pathlib import Path

import numpy as np

from etar.parsing import cannot_write_in, empty_path
from services.cli.output import say
from services.cli.zenoh_flags import zenoh_options
from services.results.text import summary_line


def ros2_rates(args):
    """The ROS 2 topics' rates the command line gives (ValueError naming the flag)."""
    from services.ros2.convert import Ros2Rates, every_nth

    rates = {f"{name}_rate_hz": getattr(args, f"ros2_{name}_rate_hz") for name in ("state", "wrench", "clock")}
    for field, value in rates.items():
        every_nth(value, f"--ros2-{field.replace('_', '-')}")
    return Ros2Rates(**rates)


def ros2_rate_flags(args) -> tuple:
    """The ROS 2 node's flags for the rates given on the command line."""
    rates = ros2_rates(args)
    return tuple(part for name in ("state", "wrench", "clock")
                 for part in (f"--{name}-rate-hz", repr(getattr(rates, f"{name}_rate_hz"))))


def run_zenoh(args):
    """The run's Zenoh session from --connect and the flags that go with it, each value checked
    as a service checks it; None: the runner makes its own on loopback and gives it to the
    services it starts.  The same options go to the runner's session and to every service,
    so without --connect nothing links them: --listen, --cfg and --mode need it; and a run
    in one process has no Zenoh at all (ValueError naming the flag for either)."""
    given = [("--connect", v) for v in args.connect or ()] + [("--listen", v) for v in args.listen or ()]
    given += [("--cfg", v) for v in args.cfg]
    if args.mode is not None:  # typed: $ETAR_ZENOH_MODE is a default, not a choice
        given.append(("--mode", args.mode))
    if not given:
        return None
    options = zenoh_options(argparse.Namespace(**{**vars(args), "connect": args.connect or []}))
    flag, value = given[0]
    if args.transport == "inproc":
        raise ValueError(f"{flag} {value}: a Zenoh flag; --transport inproc runs every node in this process, "
                         "without Zenoh: it needs --transport zenoh")
    if not args.connect:
        raise ValueError(f"{flag} {value}: needs --connect ENDPOINT: the runner and its services share the Zenoh "
                         "flags only on a session they join; without --connect the runner makes its own on loopback")
    return options


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
        empty_path("--out", args.out, "the run's folder")
        zenoh = run_zenoh(args)
        scenario = load_scenario(args.scenario)
        if args.clock:
            scenario = scenario.replace("clock", args.clock)
        options = RunOptions(out=out, run_id=args.run_id, zenoh=zenoh, transport=args.transport, engine=args.engine,
                             attach=args.attach, ready_timeout=args.ready_timeout,
                             sched_fifo=args.sched_fifo_ends, realtime_profile=args.realtime_profile, tls=args.tls,
                             hosts=args.hosts, figures=not args.no_figures, foxglove=args.foxglove,
                             replace=args.replace, command=args.command_line, wire=args.wire, ros2=args.ros2,
                             ros2_args=ros2_rate_flags(args))
        runner = Runner(scenario, options, progress=say)
    except (ScenarioError, TaskError, CredentialsError, HostsError, ValueError) as exc:
        # every option refused before anything started (services.run.options)
        say(f"etar-bench run: error: {exc}")
        return 2
    # SIGTERM (kill, docker stop) takes the same way out as Ctrl-C: the runner stops the
    # services it started and writes what it has; otherwise they outlive it as orphans
    signal.signal(signal.SIGTERM, interrupt)
    try:
        report = runner.run()  # attached, it leaves SIGTERM ignored (Runner._ignore_the_ending)
    except FileWriteError as exc:  # a full disk, a folder made read-only: what was kept stays readable
        say(f"etar-bench run: failed: {exc}; what was kept is in {out} (etar-bench info {out})")
        return 1
    except KeyboardInterrupt as exc:
        written = (Path(out) / "report.json").exists()
        say(f"etar-bench run: interrupted ({str(exc) or 'SIGINT'}); services stopped; "
             + (f"partial report in {out}" if written else "no report was written"))
        return 130
    print(runner.record.report_text)
    say(f"report: {out}/report.json, {out}/report.txt; recordings in {out}/recordings")
    # the last line, for a newcomer: what came out and where to read more
    print(summary_line(report, out, page=not args.no_figures), flush=True)
    return 0 if report["error"] is None else 1


def cmd_serve(args) -> int:
    """The simulated cell alone, for a lab's own FRI remote and Net F/T client."""
    from services.run.options import RunOptions
    from services.run.runner import Runner
    from services.run.serve import ServeOptions
    from services.scenario import ScenarioError, load_scenario

    try:
        empty_path("--out", args.out, "the folder for the recording and the report")
        scenario = load_scenario(args.scenario).replace("clock", "realtime")
        ports = ()
        for flag, value in (("--netft-rdt-port", args.netft_rdt_port), ("--netft-http-port", args.netft_http_port),
                            ("--netft-calibration-port", args.netft_calibration_port)):
            if value is not None:
                ports += (flag, str(value))
        serve = ServeOptions(fri_remote=args.fri_remote, fri_bind=args.fri_bind, krl=args.krl,
                             netft=None if args.netft == "none" else args.netft, netft_ports=ports,
                             start=args.start, max_seconds=args.max_seconds, fri_cycle_ms=args.fri_cycle_ms)
        check_robot_flags(tuple(args.robot_flag or ()), serve)
        options = RunOptions(out=args.out, run_id=args.run_id, realtime_profile=args.realtime_profile,
                             figures=False, replace=args.replace, command=args.command_line, serve=serve,
                             robot_args=tuple(args.robot_flag or ()), ros2=args.ros2,
                             ros2_args=ros2_rate_flags(args))
        runner = Runner(scenario, options, progress=say)
    except (ScenarioError, ValueError) as exc:
        say(f"etar-bench serve: error: {exc}")
        return 2
    signal.signal(signal.SIGTERM, interrupt)
    try:
        report = runner.run()
    except KeyboardInterrupt:
        written = (Path(args.out) / "report.json").exists()
        say("etar-bench serve: interrupted; services stopped; "
             + (f"report in {args.out}" if written else "no report was written"))
        return 130
    print(runner.record.report_text, flush=True)
    say(f"report: {args.out}/report.json, {args.out}/report.txt; recording in {args.out}/recordings")
    return 0 if report["error"] is None else 1


def check_robot_flags(flags: tuple, serve) -> None:
    """``--robot-flag`` values as the runner gives them to the robot after the serve's own:
    ValueError ``--robot-flag <flag> <value>: <problem>`` now, not once the run is set up."""
    from services.nodes import RobotConfig
    from services.runtime.config import with_flags

    try:
        with_flags(with_flags(RobotConfig(), serve.robot_flags()), flags, who="etar-robot")
    except ValueError as exc:
        raise ValueError(f"--robot-flag {exc}") from None


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
        say(f"etar-bench check: error: {exc}")
        return 2
    print(scenario.to_yaml(), end="", flush=True)
    kinds = {}
    for _, kind, _, _, _ in found.starts:
        kinds[EPISODE_NAMES[kind]] = kinds.get(EPISODE_NAMES[kind], 0) + 1
    episodes = ", ".join(f"{n} {kind}{'s' if n > 1 else ''}" for kind, n in kinds.items()) or "no episodes"
    model = f"; model {scenario.model_path()} loads ({found.model.n_phases} phases)" if found.model else ""
    say(f"{args.scenario}: valid: {episodes}, every start within the arm's reach{model}")
    return 0


def cmd_demo(args) -> int:
    """One demonstration by the teacher, run by the nodes in one process; its recording,
    and on request a picture and the arrays ``etar learn`` reads."""
    from services.recordings.demonstrations import load_demonstration
    from services.recordings.format import RecordingError
    from services.run.demonstration import demonstration_scenario, record_demonstration
    from services.scenario import ScenarioError

    out = args.out or f"runs/demo-{args.world}-{time.strftime('%Y%m%d-%H%M%S')}"
    try:
        empty_path("--out", args.out, "the run's folder")
        for flag, path in (("--png", args.png), ("--npz", args.npz)):
            output_file(flag, path)
    except ValueError as exc:
        say(f"etar-bench demo: error: {exc}")
        return 2
    try:
        scenario = demonstration_scenario(args.world, side=args.side, seed=args.seed, spread=args.spread,
                                          max_seconds=args.max_seconds)
    except ScenarioError as exc:
        field = exc.path.rsplit(".", 1)[-1]
        flag = {"sides": "--side", "start_spread": "--spread", "start": "--spread", "goal_x": "--spread",
                "max_seconds": "--max-seconds"}.get(field, f"--{field}")
        say(f"etar-bench demo: error: {flag}: {exc.problem}" + (f", got {exc.value!r}" if exc.has_value else ""))
        return 2
    try:
        report, recording = record_demonstration(scenario, out, progress=say, replace=args.replace)
    except ValueError as exc:  # the run folder: a file, or one that holds a run
        say(f"etar-bench demo: error: {exc}")
        return 2
    if report["error"] is not None:
        say(f"etar-bench demo: the demonstration failed: {report['error']} (run folder {out})")
        return 1
    (d,) = report["demonstrations"]
    try:
        demo = load_demonstration(recording)
    except RecordingError as exc:  # e.g. too short to give two samples
        say(f"etar-bench demo: the demonstration ended {d['reason']} after {d['sim_seconds']:.3f} s simulated and "
             f"gives no demonstration to learn from: {exc}")
        return 1
    counts = np.bincount(demo["phases"]).tolist()
    say(f"{args.world} demonstration ({args.side}): {d['reason']} after {d['sim_seconds']:.2f} s simulated, "
         f"{len(demo['states'])} samples at {1 / demo['dt']:.0f} Hz, steps per true phase {counts}; "
         f"recording {recording}")
    try:
        write_demonstration(args, demo)
    except OSError as exc:  # a disk that filled during the run: the recording is kept
        say(f"etar-bench demo: failed: {exc}; the recording is kept: {recording}")
        return 1
    if d["reason"] != "teacher_done":
        say(f"etar-bench demo: the teacher did not finish the task (the demonstration ended {d['reason']}): exit 1; "
            f"its recording and files are kept")
        return 1
    return 0


def output_file(flag: str, path) -> None:
    """ValueError ``<flag> <path>: <problem>`` unless ``path`` (None: not asked for) is a file
    this process can write: checked before the demonstration runs, not after."""
    if path is None:
        return
    empty_path(flag, path, "the file to write")
    folder = Path(path).expanduser().resolve().parent
    if Path(path).expanduser().is_dir():
        raise ValueError(f"{flag} {path}: a folder; {flag} names the file to write")
    if not folder.is_dir():
        raise ValueError(f"{flag} {path}: the folder {Path(path).parent} does not exist")
    why = cannot_write_in(folder)
    if why:
        raise ValueError(f"{flag} {path}: cannot write in {folder} ({why})")


def write_demonstration(args, demo: dict) -> None:
    """The picture (--png) and the arrays (--npz) of a demonstration, each at exactly the
    path given (numpy's own savez would add .npz to a name without it)."""
    from robot_sim.world.labels import LABELERS
    from services.runtime.files import write_via

    if args.png:
        from services.results.figures.demonstrations import demonstration_figure

        demonstration_figure(demo, Path(args.png), f"{args.world} demonstration (seed {args.seed})",
                             LABELERS[args.world].names)
        say(f"wrote {args.png}")
    if args.npz:
        def savez(tmp: Path) -> None:
            with open(tmp, "wb") as f:
                np.savez(f, states=demo["states"], forces=demo["forces"], phases=demo["phases"],
                         dt=np.float64(demo["dt"]), t=demo["t"])
        write_via(args.npz, savez)
        say(f"wrote {args.npz} " + (f"(etar learn {args.npz} ... reads it)" if args.npz.endswith(".npz") else
                                    "(etar learn reads it once its name ends .npz)"))


def cmd_sweep(args) -> int:
    from etar.task import TaskError
    from services.run.sweep import Parameter, SweepError, SweepInterrupted, sweep
    from services.scenario import ScenarioError, load_scenario

    signal.signal(signal.SIGTERM, interrupt)  # kill: the same way out as Ctrl-C
    try:
        params = [Parameter.parse(p) for p in args.param]
        result = sweep(load_scenario(args.scenario), params, repeats=args.repeats, out=args.out, record=args.record,
                       workers=args.workers, cluster=args.cluster, learn_threads=args.learn_threads,
                       replace=args.replace, say=say, engine=args.engine)
    except (SweepError, ScenarioError, TaskError) as exc:
        say(f"etar-bench sweep: error: {exc}")
        return 2
    except SweepInterrupted as stop:
        s = stop.summary or {}
        say(f"etar-bench sweep: interrupted ({stop.why}): {s.get('runs', 0)} run(s) finished"
             + (f", their table {s['table']} (sweep.json marked incomplete)" if s.get("table") else ", no table")
             + f"; {len(s.get('interrupted_runs', []))} interrupted (their partial reports under {args.out}/runs), "
             f"{len(s.get('not_started', []))} not started"
             + (f", {len(s['cancelled_on_cluster'])} cancelled on the cluster" if s.get("cancelled_on_cluster")
                else ""))
        return 130
    except KeyboardInterrupt as exc:  # before any run started
        say(f"etar-bench sweep: interrupted ({str(exc) or 'SIGINT'}) before any run started")
        return 130
    except OSError as exc:  # a scheduler that does not answer, a disk that filled: what ran is in --out
        say(f"etar-bench sweep: failed: {' '.join(str(exc).split())} (the sweep's folder: {args.out})")
        return 1
    where = result["cluster"] or f"{result['workers']} local processes"
    print(f"sweep: {result['runs']} runs ({result['failed']} failed) in {result['wall_seconds']:.0f} s on {where}; "
          f"table {result['table']}; plots {', '.join(result['plots']) or 'none'}", flush=True)
    return 0 if result["failed"] == 0 else 1


def interrupt(signum, frame):
    """A signal handler: the signal (SIGTERM) ends the command the way Ctrl-C does."""
    raise KeyboardInterrupt(signal.Signals(signum).name)

