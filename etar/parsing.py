"""The command lines' parser, for ``etar`` and every program of the testbench (which import
it from here, the lowest package with a command line): a usage error is one line on stderr,
``<prog>: error: <flag> <value>: <problem>``, exit code 2 (argparse's own prints the usage
first and words its errors ``argument --flag: ...``).  The standard library only: a
program's ``--help`` loads nothing else through it."""

from __future__ import annotations

import argparse
import re


class OneLineErrorParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line on stderr,
    ``<prog>: error: <flag> <value>: <problem>``, and exit code 2 (argparse's own prints
    the usage first and words its errors ``argument --flag: ...``)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {one_line_error(message)}\n")


def one_line_error(message: str) -> str:
    """argparse's error ``message`` worded ``<flag> <value>: <problem>`` on one line."""
    message = one_line(message)
    m = re.fullmatch(r"argument (?P<flag>[^:]+): (?P<rest>.*)", message)
    if m is None:
        m = re.fullmatch(r"the following arguments are required: (.*)", message)
        if m:
            return f"{m.group(1)}: required"
        m = re.fullmatch(r"unrecognized arguments: (.*)", message)
        if m:
            return f"{m.group(1)}: not a flag of this program (see --help)"
        return message
    flag, rest = m.group("flag").split("/")[-1], m.group("rest")
    if rest.startswith((flag + " ", flag + ":")):
        return rest  # a type of ours names the flag and the value itself
    c = re.fullmatch(r"invalid choice: (?P<value>.*?) \(choose from (?P<choices>.*)\)", rest)
    if c:
        return f"{flag} {_unquoted(c.group('value'))}: not one of {c.group('choices').replace(chr(39), '')}"
    c = re.fullmatch(r"invalid (?P<kind>\w+) value: (?P<value>.*)", rest)
    if c:
        wanted = {"int": "an integer", "float": "a number"}.get(c.group("kind"), f"a {c.group('kind')}")
        return f"{flag} {_unquoted(c.group('value'))}: expected {wanted}"
    c = re.fullmatch(r"ignored explicit argument (?P<value>.*)", rest)
    if c:
        return f"{flag} {_unquoted(c.group('value'))}: this flag takes no value"
    if rest.startswith("expected "):
        return f"{flag}: {rest.replace('argument', 'value')}"
    return f"{flag}: {rest}"


def _unquoted(text: str) -> str:
    return text[1:-1] if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"" else text


def one_line(text) -> str:
    """Any error's text on one line (its whitespace runs as single spaces)."""
    return " ".join(str(text).split())
