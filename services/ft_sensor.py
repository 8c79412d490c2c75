"""``etar-ft-sensor``: the ft_sensor node (``services.nodes.ft_sensor``) in its own process over Zenoh."""

import sys

from services.runtime.process import node_process

build_parser, main, cli = node_process("ft_sensor")

if __name__ == "__main__":
    sys.exit(cli())
