"""A node's configuration as a frozen dataclass whose fields are its command-line flags.

Each field made with ``option(default, help)`` becomes ``--field-name`` (or the
``flag`` given): the process entry point parses flags into the dataclass
(``config_from_args``), and the runner turns a config back into the flags of the
process it spawns (``config_to_args``), so a parameter is named once.  Types
come from the defaults: int, float, str, bool (a ``--flag``/``--no-flag`` pair),
or None (an optional string).
"""

from __future__ import annotations

import argparse
import dataclasses


def option(default, help: str, *, choices=None, flag: str | None = None, metavar: str | None = None):
    return dataclasses.field(default=default, metadata={"help": help, "choices": choices, "flag": flag,
                                                        "metavar": metavar})


def _flag(f: dataclasses.Field) -> str:
    return f.metadata.get("flag") or "--" + f.name.replace("_", "-")


def _fields(cls):
    return [f for f in dataclasses.fields(cls) if "help" in f.metadata]


def add_config_arguments(parser: argparse.ArgumentParser, cls) -> None:
    for f in _fields(cls):
        meta, default = f.metadata, f.default
        if isinstance(default, bool):
            parser.add_argument(_flag(f), dest=f.name, action=argparse.BooleanOptionalAction, default=default,
                                help=meta["help"])
            continue
        kind = type(default) if default is not None else str
        parser.add_argument(_flag(f), dest=f.name, type=_typed(kind, _flag(f)), default=default,
                            choices=meta.get("choices"), metavar=meta.get("metavar"),
                            help=f"{meta['help']} (default {default})")


def _typed(kind, flag):
    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} expects {kind.__name__}, got {text!r}") from None
        if kind is float and value != value:
            raise argparse.ArgumentTypeError(f"{flag} expects a number, got {text!r}")
        return value
    parse.__name__ = kind.__name__
    return parse


def config_from_args(cls, args: argparse.Namespace):
    return cls(**{f.name: getattr(args, f.name) for f in _fields(cls)})


def config_to_args(config) -> list[str]:
    """The flags that make ``config_from_args`` rebuild ``config`` (defaults left out)."""
    out = []
    for f in _fields(type(config)):
        value = getattr(config, f.name)
        if value == f.default:
            continue
        if isinstance(f.default, bool):
            out.append(_flag(f) if value else "--no-" + _flag(f)[2:])
        elif value is not None:
            out += [_flag(f), repr(value) if isinstance(value, float) else str(value)]
    return out


def with_flags(config, flags):
    """``config`` with command-line ``flags`` of its own applied (e.g. the fault
    injection flags a bench gives the robot), for a node built in this process."""
    flags = list(flags)
    if not flags:
        return config
    parser = argparse.ArgumentParser(prog=type(config).__name__, add_help=False, exit_on_error=False)
    add_config_arguments(parser, type(config))
    parser.set_defaults(**{f.name: getattr(config, f.name) for f in _fields(type(config))})
    try:
        args = parser.parse_args(flags)
    except (argparse.ArgumentError, SystemExit) as exc:
        raise ValueError(f"{type(config).__name__}: bad flags {flags}: {exc}") from None
    return config_from_args(type(config), args)
