"""``etar-recorder``: the recorder node (``services.nodes.recorder``) in its own process over Zenoh."""

import sys

from services.runtime.process import node_process

build_parser, main, cli = node_process("recorder")

if __name__ == "__main__":
    sys.exit(cli())
