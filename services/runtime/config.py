"""A node's configuration as a frozen dataclass whose fields are its command-line flags.

Each field made with ``option(default, help)`` becomes ``--field-name`` (or the
``flag`` given): the process entry point parses flags into the dataclass
(``config_from_args``), and the runner turns a config back into the flags of the
process it spawns (``config_to_args``), so a parameter is named once.  Types
come from the defaults: int, float, str, bool (a ``--flag``/``--no-flag`` pair),
or None (an optional string).  A field made with ``nested(spec, prefix)`` holds a
frozen dataclass defined elsewhere (``robot_sim.fri.LinkFaultSpec``): each of its
fields is a flag ``--<prefix><field>``, its help the field's ``doc`` metadata.
"""

from __future__ import annotations

import argparse
import dataclasses


def option(default, help: str, *, choices=None, flag: str | None = None, metavar: str | None = None):
    return dataclasses.field(default=default, metadata={"help": help, "choices": choices, "flag": flag,
                                                        "metavar": metavar})


def nested(default, prefix: str):
    """A field holding the frozen dataclass ``default`` is an instance of; its fields are
    flags named ``--<prefix><field>``."""
    return dataclasses.field(default=default, metadata={"nested": prefix})


def _flag(f: dataclasses.Field) -> str:
    return f.metadata.get("flag") or "--" + f.name.replace("_", "-")


def _fields(cls):
    """The config's flags: its options, and each nested spec's fields (renamed with the
    prefix, carrying the spec's doc as help and its default)."""
    out = []
    for f in dataclasses.fields(cls):
        if "help" in f.metadata:
            out.append(f)
        elif "nested" in f.metadata:
            for g in dataclasses.fields(type(f.default)):
                flat = dataclasses.field(default=getattr(f.default, g.name), metadata={"help": g.metadata["doc"]})
                flat.name = f.metadata["nested"] + g.name
                out.append(flat)
    return out


def _nested(cls):
    return [(f.name, type(f.default), f.metadata["nested"]) for f in dataclasses.fields(cls) if "nested" in f.metadata]


def _values(config) -> dict:
    """Flag name -> value of ``config`` (a nested spec's fields under their prefixed names)."""
    out = {f.name: getattr(config, f.name) for f in dataclasses.fields(config) if "help" in f.metadata}
    for name, spec_cls, prefix in _nested(type(config)):
        spec = getattr(config, name)
        out.update({prefix + g.name: getattr(spec, g.name) for g in dataclasses.fields(spec_cls)})
    return out


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
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if "help" in f.metadata}
    for name, spec_cls, prefix in _nested(cls):
        try:
            values[name] = spec_cls(**{g.name: getattr(args, prefix + g.name) for g in dataclasses.fields(spec_cls)})
        except ValueError as exc:
            if getattr(exc, "field", None) is None:
                raise
            # the spec names its own field (robot_sim.fri.LinkFaultError): say the flag instead
            raise ValueError(f"--{(prefix + exc.field).replace('_', '-')}: {exc.problem}, got {exc.value!r}") from None
    return cls(**values)


def config_to_args(config) -> list[str]:
    """The flags that make ``config_from_args`` rebuild ``config`` (defaults left out)."""
    out = []
    values = _values(config)
    for f in _fields(type(config)):
        value = values[f.name]
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
    parser.set_defaults(**_values(config))
    try:
        args = parser.parse_args(flags)
    except (argparse.ArgumentError, SystemExit) as exc:
        raise ValueError(f"{type(config).__name__}: bad flags {flags}: {exc}") from None
    return config_from_args(type(config), args)
