"""A node's configuration as a frozen dataclass whose fields are its command-line flags.

Each field made with ``option(default, help)`` becomes ``--field-name`` (or the
``flag`` given): the process entry point parses flags into the dataclass
(``config_from_args``), and the runner turns a config back into the flags of the
process it spawns (``config_to_args``), so a parameter is named once.  Types
come from the defaults: int, float, str, bool (a ``--flag``/``--no-flag`` pair),
or None (an optional string).  A flag's help is the field's, with its default
added (unless the help says its own), and its value's name (``metavar``) is the one
given or says the unit its name ends in (``_s``: S, ``_ms``: MS, ``_hz``: HZ), P for
a probability, or its type (N, NUMBER, TEXT).  A config that refuses a value raises
``FieldError`` (or a ValueError whose message begins with the field's name):
``config_from_args`` words it ``<flag> <value>: <problem>``.  A field made with
``nested(spec, prefix)`` holds a frozen dataclass defined elsewhere
(``robot_sim.krc.faults.LinkFaultSpec``): each of its fields is a flag
``--<prefix><field>``, its help the field's ``doc`` metadata.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
from pathlib import Path


def option(default, help: str, *, choices=None, flag: str | None = None, metavar: str | None = None):
    return dataclasses.field(default=default, metadata={"help": help, "choices": choices, "flag": flag,
                                                        "metavar": metavar})


class FieldError(ValueError):
    """A config's field refuses its value; ``str()`` names the field, a command line the flag."""

    def __init__(self, field: str, problem: str, value):
        super().__init__(f"{field} {value}: {problem}")
        self.field, self.problem, self.value = field, problem, value


def check_seed(seed) -> None:
    """FieldError unless ``seed`` (a node's noise generator's) is an integer >= 0, as numpy takes it."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise FieldError("seed", "must be an integer >= 0", seed)


def check_stall(every_s: float, stall_ms: float) -> None:
    """FieldError for fault injection's stall (``stall_every``, ``stall_ms``) that cannot be:
    negative, or endless (inf: a stall that never ends hangs the run)."""
    for name, value in (("stall_every", every_s), ("stall_ms", stall_ms)):
        if not (math.isfinite(value) and value >= 0):
            raise FieldError(name, "must be a finite number >= 0", value)


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
                                help=meta["help"] + (" (default on)" if default else " (default off)"))
            continue
        kind = type(default) if default is not None else str
        help_text = meta["help"]
        if "default" not in help_text:
            help_text += f" (default {_shown(default) if default is not None else 'none'})"
        parser.add_argument(_flag(f), dest=f.name, type=_typed(kind, _flag(f)), default=default,
                            choices=meta.get("choices"), metavar=_metavar(f, kind), help=help_text)


_UNITS = (("_ms", "MS"), ("_hz", "HZ"), ("_s", "S"))
_KINDS = {int: "N", float: "NUMBER", str: "TEXT"}


def _metavar(f: dataclasses.Field, kind) -> str | None:
    if f.metadata.get("metavar") or f.metadata.get("choices"):
        return f.metadata.get("metavar")
    unit = next((u for suffix, u in _UNITS if f.name.endswith(suffix)), None)
    if unit is None and kind is float and f.metadata["help"].startswith("probability"):
        unit = "P"
    return unit or _KINDS.get(kind, "VALUE")


def _shown(value) -> str:
    """A value as a person writes it: 0 rather than 0.0, '' for an empty text."""
    if value == "":
        return "''"
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        return str(int(value))
    return str(value)


def _typed(kind, flag):
    wanted = {int: "an integer", float: "a number"}.get(kind, kind.__name__)

    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} {text}: expected {wanted}") from None
        if kind is float and value != value:
            raise argparse.ArgumentTypeError(f"{flag} {text}: expected a number")
        return value
    parse.__name__ = kind.__name__
    return parse


def config_from_args(cls, args: argparse.Namespace):
    """The config ``cls`` of parsed flags; a value it refuses raises ValueError worded
    ``<flag> <value>: <problem>``."""
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if "help" in f.metadata}
    for name, spec_cls, prefix in _nested(cls):
        try:
            values[name] = spec_cls(**{g.name: getattr(args, prefix + g.name) for g in dataclasses.fields(spec_cls)})
        except ValueError as exc:
            if getattr(exc, "field", None) is None:
                raise
            # the spec names its own field (robot_sim.krc.faults.LinkFaultError): say the flag instead
            raise ValueError(f"--{(prefix + exc.field).replace('_', '-')} {_shown(exc.value)}: "
                             f"{exc.problem}") from None
    try:
        return cls(**values)
    except ValueError as exc:
        raise _flag_error(cls, exc, values) from None


def _flag_error(cls, exc: ValueError, values: dict) -> ValueError:
    """``exc`` of a config's check, worded ``<flag> <value>: <problem>`` when it names a field
    (``FieldError``, or a message that begins with the field's name)."""
    fields = {f.name: f for f in _fields(cls)}
    name = getattr(exc, "field", None)
    if name in fields:
        problem = exc.problem
    else:
        text = str(exc)
        name = next((n for n in sorted(fields, key=len, reverse=True) if re.match(rf"{n}\b", text)), None)
        if name is None:
            return exc
        # "noise_scale must be ... >= 0, got -1.0": the flag and the value say the "got"
        problem = re.sub(r",? got [^,;()]*$", "", text[len(name):]).lstrip(" :")
    return ValueError(f"{_flag(fields[name])} {_shown(values.get(name))}: {problem}")


def check_files(config) -> None:
    """ValueError ``<flag> <value>: ...`` for a FILE flag (``metavar="FILE"``) of ``config``
    that names no file: a program refuses it before it starts, not when its node loads it."""
    values = _values(config)
    for f in _fields(type(config)):
        value = values[f.name]
        if f.metadata.get("metavar") == "FILE" and value is not None:
            path = Path(value)
            if not path.is_file():
                raise ValueError(f"{_flag(f)} {_shown(value)}: "
                                 + ("a folder, not a file" if path.is_dir() else "no such file"))


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


class _Refusing(argparse.ArgumentParser):
    """A parser whose usage error is a ValueError of one line, not a usage printed and an exit:
    the flags are a run's, given to a node built or spawned for it."""

    def error(self, message: str):
        from etar.parsing import one_line_error

        raise ValueError(one_line_error(message).replace("this program (see --help)", self.prog))


def with_flags(config, flags, who: str | None = None):
    """``config`` with command-line ``flags`` of its own applied (e.g. the fault
    injection flags a bench gives the robot), for a node built in this process.  A flag
    it does not take is a ValueError ``<flag> <value>: <problem>`` naming ``who`` takes
    them (default: the config's class)."""
    flags = list(flags)
    if not flags:
        return config
    parser = _Refusing(prog=who or type(config).__name__, add_help=False)
    add_config_arguments(parser, type(config))
    parser.set_defaults(**_values(config))
    return config_from_args(type(config), parser.parse_args(flags))
