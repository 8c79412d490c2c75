"""``etar-robot``: the robot node (``services.nodes.robot``) in its own process over Zenoh."""

import sys

from services.runtime.process import node_process

build_parser, main, cli = node_process("robot")

if __name__ == "__main__":
    sys.exit(cli())
