"""``etar-phase-estimator``: the phase_estimator node (``services.nodes.phase_estimator``) in its own process over Zenoh."""

import sys

from services.runtime.process import node_process

build_parser, main, cli = node_process("phase_estimator")

if __name__ == "__main__":
    sys.exit(cli())
