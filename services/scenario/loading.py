"""A scenario file read into a ``Scenario``; every problem a ``ScenarioError`` naming the file and line."""

from __future__ import annotations

import os
import re
import stat
from os import PathLike
from typing import Any

import yaml

from services.scenario.checks import ScenarioError, shorten
from services.scenario.model import Scenario

# A scenario is a few kB, a hundred values, 6 levels deep (stages[0].demonstrate.start[0]).
# Past these bounds it is no scenario: a pasted log, /dev/zero, a YAML bomb (aliases of
# aliases: a few lines that expand to billions of values), or brackets nested deeper than
# the parser's recursion goes.  Each is refused before anything is built from it.
MAX_FILE_BYTES = 1_000_000
MAX_NESTING = 32  # levels of values, the top-level mapping the first, aliases followed
MAX_VALUES = 10_000  # values in the document, each alias counted as the values it stands for
MAX_PROBLEM = 200  # characters of the YAML parser's problem (it may quote a key or an anchor)


class StrictLoader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys, reads 1e-3 as a float and refuses a document
    past MAX_NESTING or MAX_VALUES.

    PyYAML keeps the last of two equal keys silently (a pasted `count:` overrides the
    first) and, following YAML 1.1, reads exponent floats without a dot as strings.
    """

    def compose_document(self):
        self._measured: dict[str, tuple[int, int]] = {}  # anchor: (height, values)
        self._depth = self._deepest = self._values = 0
        return super().compose_document()

    def compose_node(self, parent, index):
        """PyYAML's composer, bounding the nesting and the expanded size as it goes.

        The composer recurses once per level and an alias stands for its whole anchored
        node, so both are measured here, before the constructor or a check walks them.
        """
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent):
            if event.anchor in self.anchors and event.anchor not in self._measured:
                self._refuse(f"the alias *{event.anchor} is inside its own anchor: a recursive value", event)
            height, values = self._measured.get(event.anchor, (1, 1))
            self._count(self._depth + height, values, event)
            return super().compose_node(parent, index)
        first = self._values
        self._count(self._depth + 1, 1, event)
        outer, self._deepest = self._deepest, self._depth + 1
        self._depth += 1
        try:
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
        if event.anchor is not None:
            self._measured[event.anchor] = (self._deepest - self._depth, self._values - first)
        self._deepest = max(outer, self._deepest)
        return node

    def _count(self, depth: int, values: int, event) -> None:
        self._deepest = max(self._deepest, depth)
        self._values += values
        if depth > MAX_NESTING:
            self._refuse(f"nested too deeply: more than {MAX_NESTING} levels", event)
        if self._values > MAX_VALUES:
            self._refuse(f"more than {MAX_VALUES} values, each alias counted as the values it stands for", event)

    @staticmethod
    def _refuse(problem: str, event) -> None:
        raise yaml.composer.ComposerError(None, None, problem, event.start_mark)

    def construct_yaml_int(self, node):
        try:
            return super().construct_yaml_int(node)
        except ValueError:  # Python reads at most 4300 digits (sys.get_int_max_str_digits)
            digits = sum(c.isdigit() for c in node.value)
            raise yaml.constructor.ConstructorError(None, None, f"an integer of {digits} digits: no scenario "
                                                    "value is that large", node.start_mark) from None

    def construct_mapping(self, node, deep=False):
        first_line: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                if key in first_line:
                    raise yaml.constructor.ConstructorError(
                        "while constructing a mapping", node.start_mark,
                        f"duplicate key {key!r} (first on line {first_line[key]})", key_node.start_mark)
                first_line[key] = key_node.start_mark.line + 1
            except TypeError:  # unhashable key: SafeLoader reports it
                continue
        return super().construct_mapping(node, deep=deep)


StrictLoader.add_constructor("tag:yaml.org,2002:int", StrictLoader.construct_yaml_int)
StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                  |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                  |[-+]?\.(?:inf|Inf|INF)
                  |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


def load_scenario(path: str | PathLike) -> Scenario:
    """Read and validate a scenario file; every problem is a ScenarioError naming the file."""
    source = str(path)
    if not source:  # Path("") is the working directory: "Is a directory: '.'" would puzzle
        raise ScenarioError("an empty path, expected a scenario file", source="''")
    text = _read(os.fspath(path), source)
    try:
        data = yaml.load(text, Loader=StrictLoader)
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        problem = shorten(err.problem or err.context or "invalid YAML", MAX_PROBLEM)
        column = f" (column {mark.column + 1})" if mark is not None else ""
        # An unclosed bracket is noticed lines later: say where the construct began.
        began = ""
        if err.problem and err.context and err.context_mark is not None and mark is not None \
                and err.context_mark.line != mark.line:
            began = f", {err.context} on line {err.context_mark.line + 1}"
        raise ScenarioError(f"invalid YAML: {problem}{column}{began}", source=source,
                            line=mark.line + 1 if mark is not None else None) from None
    except yaml.reader.ReaderError as err:  # unmarked: its place is a position in the text
        column = err.position - text.rfind("\n", 0, err.position)
        raise ScenarioError(f"invalid YAML: {str(err).splitlines()[0]} (column {column})", source=source,
                            line=text.count("\n", 0, err.position) + 1) from None
    except yaml.YAMLError as err:  # the rest of its text is an excerpt of the file over lines
        raise ScenarioError(f"invalid YAML: {shorten(str(err).splitlines()[0], MAX_PROBLEM)}",
                            source=source) from None
    if data is None:
        raise ScenarioError("the file is empty: expected a scenario mapping (name, world, stages)", source=source)
    return Scenario.from_dict(data, source=source)


def _read(path: str | bytes, source: str) -> str:
    """The file's text: a regular file of at most MAX_FILE_BYTES, read without waiting.

    O_NONBLOCK: opening a FIFO would otherwise wait for a writer, and Ctrl-C with it.  The
    type is taken from the open file, not the name, so it cannot change in between, and
    at most one byte past the cap is read: a file that grows, or lies about its size
    (/proc), cannot make the read endless.
    """
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as err:
        raise ScenarioError(f"cannot read the file ({err})", source=source) from err
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise ScenarioError(f"not a regular file ({_kind(info.st_mode)}), expected a scenario file",
                                source=source)
        if info.st_size > MAX_FILE_BYTES:
            raise ScenarioError(f"the file is {info.st_size} bytes, more than the {MAX_FILE_BYTES} a scenario "
                                "may be (a scenario is a few kB)", source=source)
        data = b""
        while len(data) <= MAX_FILE_BYTES:
            chunk = os.read(fd, MAX_FILE_BYTES + 1 - len(data))
            if not chunk:
                break
            data += chunk
    except OSError as err:
        raise ScenarioError(f"cannot read the file ({err})", source=source) from err
    finally:
        os.close(fd)
    if len(data) > MAX_FILE_BYTES:
        raise ScenarioError(f"the file is more than the {MAX_FILE_BYTES} bytes a scenario may be (a scenario is a "
                            "few kB)", source=source)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ScenarioError(f"cannot read the file ({err})", source=source) from err


def _kind(mode: int) -> str:
    for test, kind in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return "not a file of data"
