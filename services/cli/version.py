"""What ``--version`` says: ``<program> <version>``, and when the code runs from a git
checkout its commit and whether tracked files have changed, e.g.
``etar-robot 0.1.0 (git bebbe2b, uncommitted changes)`` (services.runtime.provenance,
which reports name the same way).

    add_version_argument(parser, "etar-robot")
"""

from __future__ import annotations

import argparse

from services.runtime.provenance import code_text


def version_text(program: str) -> str:
    return f"{program} {code_text()}"


class _VersionAction(argparse.Action):
    """``--version``: the text is made when asked for (git runs only then)."""

    def __init__(self, option_strings, program: str, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="print the program's name and version (with the git commit when run from a checkout) "
                      "and exit"):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)
        self.program = program

    def __call__(self, parser, namespace, values, option_string=None):
        print(version_text(self.program), flush=True)  # on stdout, as a program's version goes
        parser.exit(0)


def add_version_argument(parser: argparse.ArgumentParser, program: str) -> None:
    """``--version`` on ``parser``: prints ``version_text(program)`` on stdout, exit code 0."""
    parser.add_argument("--version", action=_VersionAction, program=program)
