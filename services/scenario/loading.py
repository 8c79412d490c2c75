"""A scenario file read into a ``Scenario``; every problem a ``ScenarioError`` naming the file and line."""

from __future__ import annotations

import re
from os import PathLike
from pathlib import Path
from typing import Any

import yaml

from services.scenario.checks import ScenarioError
from services.scenario.model import Scenario

class StrictLoader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys and reads 1e-3 as a float.

    PyYAML keeps the last of two equal keys silently (a pasted `count:` overrides the
    first) and, following YAML 1.1, reads exponent floats without a dot as strings.
    """

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
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise ScenarioError(f"cannot read the file ({err})", source=source) from err
    try:
        data = yaml.load(text, Loader=StrictLoader)
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        problem = err.problem or err.context or "invalid YAML"
        column = f" (column {mark.column + 1})" if mark is not None else ""
        # An unclosed bracket is noticed lines later: say where the construct began.
        began = ""
        if err.problem and err.context and err.context_mark is not None and mark is not None \
                and err.context_mark.line != mark.line:
            began = f", {err.context} on line {err.context_mark.line + 1}"
        raise ScenarioError(f"invalid YAML: {problem}{column}{began}", source=source,
                            line=mark.line + 1 if mark is not None else None) from None
    except yaml.YAMLError as err:
        raise ScenarioError(f"invalid YAML: {err}", source=source) from None
    if data is None:
        raise ScenarioError("the file is empty: expected a scenario mapping (name, world, stages)", source=source)
    return Scenario.from_dict(data, source=source)


