"""``etar-impedance-commander``: the impedance_commander node (``services.nodes.impedance_commander``) in its own process over Zenoh."""

import sys

from services.runtime.process import node_process

build_parser, main, cli = node_process("impedance_commander")

if __name__ == "__main__":
    sys.exit(cli())
