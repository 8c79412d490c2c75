"""The command lines' parser and what every program shares about its command line, for
``etar`` and every program of the testbench (which import it from here, the lowest package
with a command line): a usage error is one line on stderr, ``<prog>: error: <flag> <value>:
<problem>``, exit code 2 (argparse's own prints the usage first and words its errors
``argument --flag: ...``); an output path is asked whether it can be written; output whose
reader left ends quietly.  The standard library only: a program's ``--help`` loads nothing
else through it."""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile

READER_GONE = 141  # whoever read the output stopped (`| head`): as a program SIGPIPE ends


class OneLineErrorParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line on stderr,
    ``<prog>: error: <flag> <value>: <problem>``, and exit code 2 (argparse's own prints
    the usage first and words its errors ``argument --flag: ...``)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {one_line_error(message)}\n")


class CommandParser(OneLineErrorParser):
    """A OneLineErrorParser that names a flag it does not know before an argument that is
    missing: ``etar --bogus`` is told that --bogus is no flag, not that a command is required."""

    def parse_known_args(self, args=None, namespace=None):
        self._given = list(sys.argv[1:] if args is None else args)
        # before its command: a flag unknown here is named before the command's own parser
        # says what the command misses (``etar-bench --bogus run``: not "scenario: required")
        commands = {name for a in self._actions if isinstance(a, argparse._SubParsersAction) for name in a.choices}
        if commands:
            before = next((i for i, a in enumerate(self._given) if a in commands or a == "--"), len(self._given))
            unknown = self._unknown_flag(self._given[:before])
            if unknown is not None:
                self.error(f"unrecognized arguments: {unknown}")
        return super().parse_known_args(args, namespace)

    def error(self, message: str):
        given = self._given[:self._given.index("--")] if "--" in self._given else self._given
        if message.startswith("the following arguments are required"):
            message = next((f"unrecognized arguments: {a}" for a in [self._unknown_flag(given)] if a), message)
        missing = re.fullmatch(r"argument (?P<flags>[^:]+): expected one argument", message)
        if missing:
            # argparse takes a value that begins with '-' (``--pair -1,0``) for a flag
            for flag in missing["flags"].split("/"):
                after = given[given.index(flag) + 1:given.index(flag) + 2] if flag in given else []
                if after and after[0].startswith("-"):
                    message += f"; {after[0]} begins with '-', as a flag does: give it as {flag}={after[0]}"
                    break
        super().error(message)

    def _unknown_flag(self, given: list) -> str | None:
        """The first of ``given`` that is a flag this parser does not know, or None."""
        for a in given:
            # _parse_optional: None for a value, else (action, ...) of the flag it is, or a list of them
            f = self._parse_optional(a)
            if f is not None and all(g[0] is None for g in (f if isinstance(f, list) else [f])):
                return a
        return None


def empty_path(flag: str | None, value, names: str) -> None:
    """ValueError for a path given as '' (Path('') is the current folder, where the work would
    land unasked); ``flag`` None for a positional argument; ``names``: what the path names."""
    if value is not None and not str(value).strip():
        if flag is None:
            raise ValueError(f"{value!r}: an empty path; give {names}")
        raise ValueError(f"{flag} {value!r}: an empty path; {flag} names {names}")


def cannot_write_in(folder) -> str | None:
    """Why this process cannot make files in the existing ``folder``, or None: asked by making and
    removing an empty folder there, as os.access says yes to root anywhere, /proc included."""
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".etar-probe-", dir=folder))
    except OSError as exc:
        return exc.strerror or str(exc)
    return None


def reader_gone() -> int:
    """The output's reader closed it: say nothing more (stdout onto /dev/null, so that the
    interpreter's last flush does not complain) and exit as a program SIGPIPE ends."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return READER_GONE


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
            first = m.group(1).split()[0]
            if first.startswith("-"):
                return f"{m.group(1)}: not a flag of this program (see --help)"
            return f"{m.group(1)}: more arguments than this program takes (see --help)"
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
