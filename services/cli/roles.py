"""The seven service programs (``etar-robot``, ``etar-ft-sensor``, ...): one node in its own
process over Zenoh.  Each program's flags are the ones every service shares
(``--run-id``, ``--clock``, the Zenoh flags, ``--sched-fifo``, ``--cpus``) and its
node's own, from the node's config dataclass (``services.runtime.config``); its help
is the node's documentation.

    python -m services.cli.roles ROLE [flags]     (what the runner spawns)
"""

from __future__ import annotations

import argparse
import functools
import sys

import zenoh

from services.cli.zenoh_flags import add_zenoh_arguments, zenoh_options
from services.nodes import NODES
from services.runtime.config import add_config_arguments, config_from_args
from services.runtime.cycle import CLOCKS
from services.runtime.roles import ROLES
from services.transport.process import ProcessConfig, run_node
from services.transport.session import zenoh_reason


def build_parser(role: str) -> argparse.ArgumentParser:
    node_cls, config_cls = NODES[role]
    parser = argparse.ArgumentParser(prog=ROLES[role].program, description=sys.modules[node_cls.__module__].__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-id", required=True, help="run id: topics live under etar/<run-id>/")
    parser.add_argument("--clock", choices=CLOCKS, default="lockstep",
                        help="lockstep: every cycle waits for its answers (deterministic); "
                             "realtime: 1 ms wall-clock deadlines (default lockstep)")
    add_config_arguments(parser.add_argument_group(role.replace("_", " ")), config_cls)
    add_zenoh_arguments(parser)
    return parser


def main(role: str, argv=None) -> int:
    """The program of ``role``: parse, build the node's config, run it until shut down."""
    program = ROLES[role].program
    args = build_parser(role).parse_args(argv)
    try:
        node_config = config_from_args(NODES[role][1], args)
        process = ProcessConfig(run_id=args.run_id, zenoh=zenoh_options(args), clock=args.clock,
                                sched_fifo=args.sched_fifo, cpus=args.cpus)
        return run_node(role, node_config, process)
    except (ValueError, OSError) as exc:
        print(f"{program}: error: {exc}", file=sys.stderr)
        return 2
    except zenoh.ZError as exc:  # e.g. an endpoint it cannot listen on
        print(f"{program}: error: zenoh: {zenoh_reason(exc)}", file=sys.stderr)
        return 2


# the console scripts (pyproject.toml): one program per role
robot = functools.partial(main, "robot")
ft_sensor = functools.partial(main, "ft_sensor")
teacher = functools.partial(main, "teacher")
phase_estimator = functools.partial(main, "phase_estimator")
impedance_commander = functools.partial(main, "impedance_commander")
recorder = functools.partial(main, "recorder")
foxglove_bridge = functools.partial(main, "foxglove_bridge")


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] not in ROLES:
        sys.exit(f"usage: python -m services.cli.roles ROLE [flags]  (ROLE: {', '.join(ROLES)})")
    sys.exit(main(sys.argv[1], sys.argv[2:]))
