"""The eight service programs (``etar-robot``, ``etar-ft-sensor``, ...): one node in its own
process over Zenoh.  Each program's flags are the ones every service shares
(``--run-id``, ``--clock``, the Zenoh flags, ``--sched-fifo``, ``--cpus``) and its
node's own, from the node's config dataclass (``services.runtime.config``); its help
is the node's documentation (its module docstring, ``help_text`` drops the reST markup).

A mistake on the command line is refused before anything starts (no session opened,
no "ready" line): one line on stderr, ``<program>: error: <flag> <value>: <problem>``,
exit code 2.  ``--version`` says the program's version (``services.cli.version``).

    python -m services.cli.roles ROLE [flags]     (what the runner spawns)
"""

from __future__ import annotations

import argparse
import functools
import re
import sys

import zenoh

from etar.parsing import CommandParser
from services.cli.version import add_version_argument
from services.cli.zenoh_flags import add_zenoh_arguments, zenoh_options
from services.nodes import NODES
from services.runtime.config import add_config_arguments, check_files, config_from_args
from services.runtime.cycle import CLOCKS
from services.runtime.roles import ROLES
from services.runtime.topics import check_run_id
from services.transport.process import ProcessConfig, run_node
from services.transport.session import zenoh_reason


def help_text(doc: str | None) -> str:
    """A docstring as a person reads it in ``--help``: reST's ``literal`` markup dropped."""
    return re.sub(r"``(.+?)``", r"\1", doc or "", flags=re.DOTALL)


def run_id(text: str) -> str:
    """A ``--run-id`` value (``services.runtime.topics.check_run_id``)."""
    try:
        return check_run_id(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--run-id {text}: {str(exc).split(': ', 1)[-1]}") from None


def build_parser(role: str) -> argparse.ArgumentParser:
    node_cls, config_cls = NODES[role]
    program = ROLES[role].program
    parser = CommandParser(prog=program, description=help_text(sys.modules[node_cls.__module__].__doc__),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    add_version_argument(parser, program)
    parser.add_argument("--run-id", required=True, type=run_id, metavar="ID",
                        help="the run's id: 1-64 letters, digits, '-' or '_'; topics live under etar/ID/ (required)")
    parser.add_argument("--clock", choices=CLOCKS, default="lockstep",
                        help="lockstep: every cycle waits for its answers (deterministic); "
                             "realtime: 1 ms wall-clock deadlines (default lockstep)")
    add_config_arguments(parser.add_argument_group(role.replace("_", " ")), config_cls)
    add_zenoh_arguments(parser)
    return parser


def main(role: str, argv=None) -> int:
    """The program of ``role``: parse, build the node's config, run it until shut down.
    A usage error exits 2 before anything starts."""
    program = ROLES[role].program

    def refuse(problem: str) -> int:
        print(f"{program}: error: {' '.join(str(problem).split())}", file=sys.stderr, flush=True)
        return 2

    args = build_parser(role).parse_args(argv)  # argparse's own errors: SystemExit(2), one line
    try:
        node_config = config_from_args(NODES[role][1], args)
        check_files(node_config)
        process = ProcessConfig(run_id=args.run_id, zenoh=zenoh_options(args), clock=args.clock,
                                sched_fifo=args.sched_fifo, cpus=args.cpus)
    except ValueError as exc:  # a value refused: nothing has started yet
        return refuse(str(exc))
    try:
        return run_node(role, node_config, process)
    except (ValueError, OSError) as exc:
        return refuse(str(exc))
    except zenoh.ZError as exc:  # e.g. an endpoint it cannot listen on
        reason = zenoh_reason(exc)
        at = next((e for e in process.zenoh.listen if e in reason), None)
        return refuse(f"--listen {at}: {reason}" if at else f"zenoh: {reason}")


# the console scripts (pyproject.toml): one program per role
robot = functools.partial(main, "robot")
ft_sensor = functools.partial(main, "ft_sensor")
teacher = functools.partial(main, "teacher")
phase_estimator = functools.partial(main, "phase_estimator")
impedance_commander = functools.partial(main, "impedance_commander")
recorder = functools.partial(main, "recorder")
foxglove_bridge = functools.partial(main, "foxglove_bridge")
ros2 = functools.partial(main, "ros2")


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] not in ROLES:
        print(f"services.cli.roles: error: ROLE {sys.argv[1] if len(sys.argv) > 1 else ''}: expected one of "
              f"{', '.join(ROLES)} (python -m services.cli.roles ROLE [flags])", file=sys.stderr)
        sys.exit(2)
    code = main(sys.argv[1], sys.argv[2:])
    from services.runtime.threads import exit_without_teardown

    exit_without_teardown(code)  # the node and its Zenoh session are closed (``run_node``)
