"""``etar-teacher``: the teacher node (``services.nodes.teacher``) in its own process over Zenoh."""

import sys

from services.runtime.process import node_process

build_parser, main, cli = node_process("teacher")

if __name__ == "__main__":
    sys.exit(cli())
