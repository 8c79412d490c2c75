"""The Python API a notebook needs: run a scenario, get the typed record of the run.

    from services import run_scenario
    record = run_scenario("scenarios/smoke.yaml", out="runs/smoke", transport="inproc")
    record.report["summary"]["online_phase_accuracy"]

The keyword arguments are ``RunOptions``' fields (``out``, ``transport``, ``figures``,
``replace``, ``foxglove``, ...), checked by the same rules as the command line's
flags.  The run is the one ``etar-bench run`` makes: a run through the API records
exactly what the command line records for the same scenario (``etar-bench diff``).
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Mapping
from os import PathLike
from pathlib import Path

from services.results.record import RunRecord
from services.run.options import RunOptions
from services.run.runner import Runner
from services.scenario import Scenario, load_scenario

# the command line's flags whose keyword argument has another name
_KEYWORD_OF_FLAG = {"connect": "zenoh", "foxglove PORT": "foxglove"}


def _keywords(message: str) -> str:
    """A RunOptions error with its flags (--ready-timeout) named as keyword arguments."""
    def keyword(m: re.Match) -> str:
        flag = m.group(1)
        return _KEYWORD_OF_FLAG.get(flag, flag.replace("-", "_"))
    return re.sub(r"--(foxglove PORT|[a-z][a-z-]*)", keyword, message)


def run_scenario(scenario: Scenario | str | PathLike, *, out: str | PathLike | None = None, progress=print,
                 **options) -> RunRecord:
    """Run ``scenario`` (a ``Scenario`` or a YAML file's path) and return what the run did,
    its report in ``record.report`` (``record.report["error"]`` is None when it succeeded).
    ``out`` defaults to ``runs/<scenario>-<time>`` as on the command line.  An option or
    scenario that cannot be run raises (ValueError, ScenarioError, ...) before anything
    starts; a run that fails returns its record with the error in its report."""
    if isinstance(scenario, Mapping):
        scenario = Scenario.from_dict(dict(scenario), source="<run_scenario's dict>")
    elif isinstance(scenario, (str, PathLike)):
        scenario = load_scenario(scenario)
    elif not isinstance(scenario, Scenario):
        raise TypeError(f"run_scenario: scenario must be a Scenario, a dict or a YAML file's path, got "
                        f"{type(scenario).__name__}")
    known = {f.name for f in dataclasses.fields(RunOptions)} - {"out", "command"}
    unknown = sorted(set(options) - known)
    if unknown:
        raise TypeError(f"run_scenario: unknown option(s) {', '.join(unknown)}; the options are "
                        f"{', '.join(sorted(known))}")
    if out is None:
        out = f"runs/{scenario.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    shown = ", ".join(f"{k}={v!r}" for k, v in options.items())
    command = f"run_scenario({scenario.source!r}, out={str(out)!r}{', ' + shown if shown else ''})"
    try:
        run_options = RunOptions(out=str(Path(out)), command=command, **options)
    except ValueError as exc:  # RunOptions says it in the command line's words: say it in the API's
        raise ValueError(f"run_scenario: {_keywords(str(exc))}") from None
    runner = Runner(scenario, run_options, progress=progress)
    runner.record.report = runner.run()
    return runner.record
