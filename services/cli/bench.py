"""``etar-bench``: run scenarios and read their reports.

    etar-bench run SCENARIO [--out DIR] [--clock realtime|lockstep] [--transport zenoh|inproc]
                   [--engine fused|per-message] [--foxglove [PORT]] [--ros2 [DOMAIN]]
    etar-bench check SCENARIO
    etar-bench serve SCENARIO --out DIR [--fri-remote HOST:PORT] [--krl frilibrary|lwr_hw] [--netft HOST]
                     [--start X,Y,Z] [--max-seconds S] [--ros2 [DOMAIN]]
    etar-bench demo [--world valley|hose_coupler] [--side left|right] [--png FILE] [--npz FILE]
    etar-bench sweep SCENARIO --out DIR [--param PATH=V1,V2,...] [--repeats N] [--engine fused|per-message]
                     [--cluster ADDRESS]
    etar-bench report RUN_DIR [--json]
    etar-bench info PATH [--json]
    etar-bench diff RUN_A RUN_B [--json]
    etar-bench recover FILE... [--out FILE]
    etar-bench figures RUN_DIR
    etar-bench compare RUN_DIR [--seeds N] [--pair I,J]
    etar-bench export RUN_DIR --foxglove [--visual-rate-hz HZ]
    etar-bench export RUN_DIR --rosbag2 [--out DIR]
    etar-bench certs DIR [--host IP]
    etar-bench router [--listen tcp/0.0.0.0:7447]
"""

from __future__ import annotations

import argparse
import shlex
import sys

import numpy as np

from robot_sim.world.tasks import TASK_WORLDS
from etar.parsing import CommandParser, reader_gone
from services.cli.version import add_version_argument
from services.cli.network_commands import cmd_certs, cmd_router
from services.cli.result_commands import (cmd_compare, cmd_diff, cmd_export, cmd_figures, cmd_info, cmd_recover,
                                          cmd_report)
from services.cli.run_commands import cmd_check, cmd_demo, cmd_run, cmd_serve, cmd_sweep
from services.cli.zenoh_flags import add_zenoh_arguments
from services.transport.session import ZENOH_PORT
from services.runtime.visual_topics import FOXGLOVE_PORT, VISUAL_RATE_HZ


def _profile(text: str) -> str:
    from services.run.realtime_profile import parse_profile

    try:
        parse_profile(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _xyz(text: str) -> tuple:
    parts = text.split(",")
    try:
        values = tuple(float(v) for v in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z in m, e.g. 0.5,0.0,0.3; got {text!r}")
    return values


def add_ros2_arguments(p, live: bool, transport_flag: bool = True) -> None:
    """``--ros2 [DOMAIN]`` (``live``: a run or a serve) and the rates of the ROS 2 topics;
    ``transport_flag``: the command has ``--transport``, which --ros2 needs to be zenoh."""
    from services.ros2.convert import Ros2Rates

    if live:
        p.add_argument("--ros2", nargs="?", const=0, type=int, metavar="DOMAIN",
                       help="the cell on ROS 2's Zenoh wire (rmw_zenoh, Jazzy >= 0.2.4, Kilted, Rolling) as node "
                            "/etar_cell in ROS 2 domain DOMAIN (default 0): /joint_states, /tf, /robot_description, "
                            "/tcp_pose, /ft_sensor/wrench, /etar/phase, /clock (docs/ros2.md)" +
                            ("; with --transport zenoh" if transport_flag else ""))
    for name, what in (("state", "/joint_states, /tf and /tcp_pose"), ("wrench", "/ft_sensor/wrench"),
                       ("clock", "/clock")):
        p.add_argument(f"--ros2-{name}-rate-hz", type=float, default=getattr(Ros2Rates, f"{name}_rate_hz"),
                       metavar="HZ", help=f"rate of {what}, Hz, dividing 1000 (default "
                                          f"{getattr(Ros2Rates, f'{name}_rate_hz'):g})")


def build_parser() -> CommandParser:
    from services.foxglove import export
    from services.recordings import recovery
    from services.results import diff
    from services.run import demonstration, sweep
    from services.scenario.checks import SIDES
    from services.run.options import WIRES, RunOptions
    from services.runtime.cycle import CLOCKS
    from services.runtime.roles import FIFO_CHAIN
    from services.transport.carriers import ENGINES, TRANSPORTS

    from robot_sim.krc.krl import LAB_CONVENTIONS
    from services.run.serve import ServeOptions

    fifo = ", ".join(f"{role} {priority}" for role, priority in FIFO_CHAIN)
    fifo_ends = " and ".join(f"{role} ({priority})" for role, priority in RunOptions.fifo_priorities)
    parser = CommandParser(prog="etar-bench", description=__doc__,
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
    p.add_argument("--engine", choices=ENGINES,
                   help="with --transport inproc, how the FRI cycles are stepped: fused (the 1 kHz path walked "
                        "once per cycle, each node's work called directly; default) or per-message (every "
                        "message through the in-memory bus to each node's handler, the reference); the same "
                        "recordings either way")
    p.add_argument("--attach", action="store_true",
                   help="drive services that are already running (docker-compose) instead of starting them")
    p.add_argument("--ready-timeout", type=float, default=RunOptions.ready_timeout,
                   help=f"seconds to wait for the services (default {RunOptions.ready_timeout:g})")
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
    add_ros2_arguments(p, live=True)
    p.add_argument("--wire", choices=WIRES, default=RunOptions.wire,
                   help="zenoh (default): the nodes talk over Zenoh; udp: over the lab's protocols, the KRC and "
                        "the commander FRI 1.0 over UDP, the estimator reading the sensor's Net F/T box (realtime "
                        "only; docs/fri.md)")
    p.add_argument("--no-figures", action="store_true",
                   help="skip the thesis' figures and report.html after the report (etar-bench figures RUN_DIR "
                        "draws both later)")
    add_zenoh_arguments(p, process_flags=False, run=True)  # the services get theirs from the run
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
    add_ros2_arguments(p, live=True, transport_flag=False)
    p.set_defaults(func=cmd_serve)
    what = "validate a scenario without running it (the model file, every start) and print it with every " \
           "default filled in"
    p = sub.add_parser("check", help=what, description=what[0].upper() + what[1:] + "; exit 2 and one line naming "
                       "the file, the field and the value when it is not valid.")
    p.add_argument("scenario", help="scenario YAML file (see docs/scenarios.md)")
    p.set_defaults(func=cmd_check)
    what = "one demonstration by the simulated teacher, in one process: its recording, and on request a " \
           "picture and the arrays etar learn reads"
    p = sub.add_parser("demo", help=what, description=what[0].upper() + what[1:] + "; exit 1 when the teacher "
                       "did not finish the task (its files are kept), 2 on a bad flag.")
    p.add_argument("--world", choices=TASK_WORLDS, default="valley", help="the task world (default valley)")
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
                                                 "exist; checked before the demonstration runs)")
    p.add_argument("--npz", metavar="FILE", help="write its arrays to exactly this file (states, forces, phases, dt: "
                                                 "what etar learn reads, from a name ending .npz; its folder must "
                                                 "exist)")
    p.set_defaults(func=cmd_demo)
    p = sub.add_parser("sweep", help="run every combination of scenario parameters x seeds in parallel, "
                                     "in-process; a table and plots",
                       description=sweep.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenario", help="scenario YAML file (see docs/scenarios.md)")
    p.add_argument("--param", action="append", default=[], metavar="PATH=V1,V2,...",
                   help="a scenario parameter and its values, e.g. cell.sensor_noise=0.5,1,2 or "
                        "reproduce.start_perturbation=0.01,0.03 (repeatable: every combination runs)")
    p.add_argument("--repeats", type=int, default=1,
                   help=f"seeds per combination: the scenario's seed + 0..N-1; the sweep's runs, combinations x "
                        f"repeats, at most {sweep.MAX_RUNS} (each is seconds of CPU: more is days)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="the sweep's folder, created, for the table, the plots and the runs; one that holds a sweep "
                        "is refused unless --replace")
    p.add_argument("--replace", action="store_true", help="--out holds an earlier sweep: remove it first")
    p.add_argument("--record", choices=sweep.RECORD, default="summary",
                   help="what to keep of each run: everything (recordings with Foxglove's visual topics), its "
                        "report and model (default), or nothing")
    p.add_argument("--workers", type=int,
                   help=f"local processes, at most {sweep.WORKERS_PER_CPU} x the CPUs this process may use (each run "
                        "is CPU-bound and holds a cell in memory: more only share the CPUs) (default: the CPUs)")
    p.add_argument("--engine", choices=ENGINES,
                   help="how each run's FRI cycles are stepped in its process: fused (default) or per-message "
                        "(see etar-bench run --help)")
    p.add_argument("--cluster", metavar="ADDRESS",
                   help="a Dask scheduler, e.g. tcp://10.0.0.5:8786, to send the runs to instead")
    p.add_argument("--learn-threads", type=int,
                   help="numba threads per run's learner (default: the CPUs divided among the workers)")
    p.set_defaults(func=cmd_sweep)
    p = sub.add_parser("report", help="print the report of a finished run")
    p.add_argument("run_dir", help="a run's folder (its report.txt, or report.json with --json)")
    p.add_argument("--json", action="store_true", help="print report.json instead of the text")
    p.set_defaults(func=cmd_report)
    p = sub.add_parser("info", help="what a recording or a run holds: topics with schema, counts, rates, duration, "
                                    "gaps, episodes and their results, the scenario and the code that made it; "
                                    "exit 1 when a recording is incomplete or missing")
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
                                       "--no-figures); exit 1 when a recording is unreadable or cut short "
                                       "(figures.error names it)")
    p.add_argument("run_dir", help="a finished run's folder (report.json, model.json, recordings/)")
    p.set_defaults(func=cmd_figures)

    p = sub.add_parser("export", help="add Foxglove's visual topics (the arm, the world, wrench, stiffness, "
                                      "phase) to a run's recordings made without them",
                       description=export.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir", help="a finished run's folder (recordings/*.mcap)")
    p.add_argument("--foxglove", action="store_true", help="add the visual topics for Foxglove to the recordings")
    p.add_argument("--visual-rate-hz", type=float, default=VISUAL_RATE_HZ, metavar="HZ",
                   help=f"visual frames per second of simulated time (default {VISUAL_RATE_HZ:g})")
    p.add_argument("--rosbag2", action="store_true",
                   help="a ROS 2 bag (rosbag2, MCAP, CDR) of each recording, the topics of --ros2 (docs/ros2.md)")
    p.add_argument("--out", metavar="DIR", help="--rosbag2: the folder for the bags (default RUN_DIR/rosbag2)")
    add_ros2_arguments(p, live=False)
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

    what = "run a Zenoh router (for docker-compose or several hosts)"
    p = sub.add_parser("router", help=what, description=what[0].upper() + what[1:] + ", until Ctrl-C or SIGTERM.")
    p.add_argument("--listen", action="append", help=f"endpoint(s), default tcp/0.0.0.0:{ZENOH_PORT}; port 0: the "
                                                     "system chooses, and the first line says which (its read-only "
                                                     "admin space, as zenohd's, says so)")
    p.set_defaults(func=cmd_router)
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.command_line = shlex.join(["etar-bench", *argv])  # what the report says made the run
    try:
        return args.func(args)
    except BrokenPipeError:
        return reader_gone()


if __name__ == "__main__":
    sys.exit(main())
