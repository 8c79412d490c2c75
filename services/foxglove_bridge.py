"""``etar-foxglove-bridge``: the Foxglove bridge node (``services.nodes.foxglove_bridge``) in its own process over Zenoh."""

import sys

from services.runtime.process import node_process

build_parser, main, cli = node_process("foxglove_bridge")

if __name__ == "__main__":
    sys.exit(cli())
