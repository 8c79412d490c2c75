"""The command-line reference, ``docs/cli.md``, generated from the argparse parsers themselves
(as ``docs/messages.md`` is from the messages), so that it cannot drift from them:

    python -m services.cli.reference > docs/cli.md

``tests/test_docs.py`` fails when the file is not what this prints.
"""

from __future__ import annotations

import argparse
import sys
import textwrap

import etar.cli
from services.cli import bench, roles
from services.runtime.roles import ROLES


def _cell(text) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _argument(action: argparse.Action) -> str:
    if not action.option_strings:
        return f"`{action.metavar or action.dest}`"
    if isinstance(action, argparse.BooleanOptionalAction):
        return " / ".join(f"`{s}`" for s in action.option_strings)
    if action.nargs == 0:
        return f"`{action.option_strings[-1]}`"
    value = action.metavar or ("{" + ",".join(map(str, action.choices)) + "}" if action.choices
                               else action.dest.upper())
    value = f"[{value}]" if action.nargs == "?" else value
    return f"`{action.option_strings[-1]} {value}`"


def _default(action: argparse.Action) -> str:
    if not action.option_strings:
        return "required" if action.nargs not in ("?", "*") else ""
    if action.required:
        return "required"
    default = action.default
    if default is None or default is False or default is argparse.SUPPRESS or default in ([], ()) or action.nargs == 0:
        return ""
    return f"`{default}`"


def _table(parser: argparse.ArgumentParser) -> list[str]:
    rows = [a for a in parser._actions if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]
    if not rows:
        return []
    lines = ["| argument | default | meaning |", "|---|---|---|"]
    for a in rows:
        help_text = (a.help or "") % {"default": a.default, "prog": parser.prog} if a.help else ""
        lines.append(f"| {_argument(a)} | {_default(a)} | {_cell(help_text)} |")
    return lines + [""]


def _description(parser: argparse.ArgumentParser) -> list[str]:
    """The parser's description: prose as prose, indented usage lines as a code block."""
    text = textwrap.dedent(parser.description or "").strip("\n")
    if not text:
        return []
    out, block = [], []
    for paragraph in text.split("\n\n"):
        if all(line.startswith("    ") or not line.strip() for line in paragraph.splitlines()):
            block.append(textwrap.dedent(paragraph))
            continue
        if block:
            out += ["```", *"\n\n".join(block).splitlines(), "```", ""]
            block = []
        out += [" ".join(paragraph.split()), ""]
    if block:
        out += ["```", *"\n\n".join(block).splitlines(), "```", ""]
    return out


def _program(parser: argparse.ArgumentParser, level: int = 2) -> list[str]:
    lines = [f"{'#' * level} `{parser.prog}`", "", *_description(parser), *_table(parser)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                lines += [f"{'#' * (level + 1)} `{sub.prog}`", ""]
                if helps.get(name):
                    lines += [_cell(helps[name]).rstrip(".") + ".", ""]
                if sub.description and sub.description != parser.description:
                    lines += _description(sub)
                lines += _table(sub)
    return lines


def reference() -> str:
    lines = ["# Command-line reference", "",
             "Generated from the argparse parsers (`python -m services.cli.reference > docs/cli.md`); "
             "every program also answers `--help`.  A bad flag or file is refused in one line on stderr "
             "with exit code 2; a run that failed exits 1; output whose reader stops reading (`| head`) ends "
             "quietly with 141, as a program SIGPIPE ends.", "",
             "- [`etar-bench`](#etar-bench): run scenarios, sweeps and demonstrations; read, redraw, "
             "compare and export their results",
             "- [`etar`](#etar): learn ETAR models from demonstrations and inspect them",
             "- the service programs, one node each in its own process over Zenoh (the runner starts them; "
             "docker-compose too): " + ", ".join(f"`{r.program}`" for r in ROLES.values()), ""]
    lines += _program(bench.build_parser())
    lines += _program(etar.cli.build_parser())
    lines += ["## The service programs", "",
              "Each runs one node (`services/nodes/`) in its own process: `python -m services.cli.roles ROLE` "
              "is what the runner spawns.  The flags every service shares come first, then the node's own "
              "(from its config dataclass, `services.runtime.config`), then Zenoh's.", ""]
    for role in ROLES:
        lines += _program(roles.build_parser(role), level=3)
    return "\n".join(lines).rstrip("\n") + "\n"


if __name__ == "__main__":
    sys.stdout.write(reference())
