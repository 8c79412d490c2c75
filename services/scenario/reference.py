"""The scenario reference, ``docs/scenarios.md``, generated from the definition itself: every
key's default and meaning from the fields of ``Scenario``, its stages and its cell
(``robot_sim.krc.faults.LinkFaultSpec`` for the link's faults), and the table of scenario files
from the files:

    python -m services.scenario.reference scenarios > docs/scenarios.md

``tests/test_docs.py`` fails when the file is not what this prints.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

from robot_sim.krc.faults import LinkFaultSpec
from services.scenario.loading import MAX_FILE_BYTES, MAX_NESTING, MAX_VALUES, load_scenario
from services.scenario.model import Scenario
from robot_sim.world.tasks import Valley
from services.scenario.checks import MAX_PHASES, MAX_QUOTED, MAX_START_DRAWS
from services.scenario.starts import DEMONSTRATE_SEED_OFFSET, REPRODUCE_SEED_OFFSET, TEACHER_SEED_STRIDE
from services.scenario.stages import DEFAULT_STARTS, FRI_PREFIX, STAGE_TYPES, VALLEY_GOAL_X, CellSpec

INTRO = """\
A scenario is a YAML file that describes one run of the testbench: the world, the clock,
the seeds and the stages (demonstrate, learn, reproduce).  It says *what* to run, never
*how* (the transport, the output folder and the machine are the run's options,
`etar-bench run --help`).  `services/scenario/` parses it into frozen values, validated on
construction with every default filled in; loading one starts nothing, so a file can be
checked without a simulator:

```python
from services.scenario import load_scenario
scenario = load_scenario("scenarios/valley.yaml")   # a ScenarioError names the file, the field and the value
variant = scenario.replace("cell.sensor_noise", 2.0).replace("seed", 3)   # a new value, validated again
```
"""

RULES = f"""\
## Rules

- **Stage order**: `demonstrate*`, then at most one `learn`, then `reproduce*`.  A `learn`
  stage needs a `demonstrate` stage before it; a `reproduce` stage needs the `learn` stage
  before it, or a `model` file (a `model.json` a run's learn stage or `etar learn` wrote: it
  carries the per-phase impedance, the goal and the learned-to-true phase mapping), and
  then there is no `learn` stage.  A scenario of demonstrate stages only just records
  demonstrations.  A stage with nothing under it (`- learn:`) takes all its defaults.
- **Sides**: in the valley the left side is y < 0 and the right side mirrors y.  A `start`
  is always the left side's, so it must keep y < 0 with its spread (or perturbation).  The
  hose coupler has one side: omit `sides` or give `[left]`, and omit `goal_x`.
- **Goal**: `goal_x` lies below the x of every start: the valley's teacher slides towards -x.
- **Seeds** are non-negative (numpy's generators refuse negative ones).  A stage's default
  seed is the scenario's seed plus {DEMONSTRATE_SEED_OFFSET} (demonstrate), 0 (learn) or {REPRODUCE_SEED_OFFSET} (reproduce), plus j
  for the j-th stage of that kind, so two demonstrate stages that inherit the seed do not
  replay each other.  The teacher's hand in the i-th demonstration of a stage is seeded
  with the stage's seed x {TEACHER_SEED_STRIDE} + i (`services/scenario/starts.py` holds every seed rule).
- **Starts** belong to the description: `demonstration_starts(stage, world, seed)` and
  `reproduction_starts(stage, world, seed, demonstration_starts)` depend on the stage and
  the seed alone, so a run can be replayed and its report says where each episode began.
  A reproduction start closer than `min_distance_from_demonstrations` to a demonstration
  start of its side is drawn again; after {MAX_START_DRAWS} draws the scenario is refused (the
  perturbation is too small for that distance).
- **Learning**: with `phases: auto` every count in `candidates` is fitted and `criterion`
  picks one: per demonstration (the count most demonstrations choose wins, ties to fewer
  phases; thesis 6.1) or pooled over all of them.
- **Numbers** are finite (`.nan` and `.inf` are refused where a finite number is meant;
  `fri_faults_until_s: .inf` is the default), `1e-3` reads as a number, and a duplicate key
  is an error (PyYAML would keep the last one silently).
- **Errors** are one `ScenarioError` naming the file (and line, for YAML), the field and the
  value, e.g. `scenarios/x.yaml: stages[1].learn.phases: expected 'auto' or an integer >= 1
  and <= {MAX_PHASES}, got 'three'`, or `stages[0].demonstrate.cuont: unknown key (did you mean 'count'? ...)`.
  A value quoted in an error is cut to {MAX_QUOTED} characters, with its size.
- **Size**: a scenario is a regular file of at most {MAX_FILE_BYTES:,} bytes, nested at most
  {MAX_NESTING} levels deep and of at most {MAX_VALUES:,} values, an alias counted as the values it
  stands for (a few lines of aliases of aliases would otherwise expand to billions).

## Varying a scenario

`Scenario.replace(path, value)` returns a new scenario with one key set, validated as any
scenario, defaults kept defaults (a new `seed` reaches every stage that inherits it).
`path` is a top-level key (`seed`, `clock`), `cell.KEY`, `STAGE.KEY` for every stage of that
kind (`reproduce.count`) or `STAGE[i].KEY` for the i-th (`reproduce[1].start_perturbation`).
A sweep takes the same paths (`etar-bench sweep SCENARIO --param PATH=V1,V2,...`), and every
recording attaches the scenario it ran, serialised from the value (`Scenario.to_yaml`).
"""


def _value(value) -> str:
    if value is dataclasses.MISSING:
        return "required"
    if value is None:
        return "-"
    if isinstance(value, float) and math.isinf(value):
        return "`.inf`"
    if isinstance(value, tuple):
        return "`[" + ", ".join(map(str, value)) + "]`"
    if isinstance(value, str):
        return f"`{value}`" if value else '`""`'
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    return f"`{value}`"


def _esc(text: str) -> str:
    return text.replace("|", "\\|")


def _rows(cls, prefix: str = "") -> list[str]:
    rows = []
    for f in dataclasses.fields(cls):
        if "doc" not in f.metadata:
            continue
        default = f.default if f.default_factory is dataclasses.MISSING else f.default_factory()
        if isinstance(default, (CellSpec, LinkFaultSpec)) or f.name in ("cell", "stages"):
            default = "see below" if f.name != "stages" else "required"
            rows.append(f"| `{prefix}{f.name}` | {default} | {_esc(f.metadata['doc'])} |")
            continue
        rows.append(f"| `{prefix}{f.name}` | {_value(default)} | {_esc(f.metadata['doc'])} |")
    return rows


def _table(rows) -> list[str]:
    return ["| key | default | meaning |", "|---|---|---|", *rows, ""]


def _files(folder: Path) -> list[str]:
    lines = ["| file | world | stages | what |", "|---|---|---|---|"]
    for path in sorted(folder.glob("*.yaml")):
        s = load_scenario(path)
        stages = ", ".join(f"{st.kind} {st.count}" if hasattr(st, "count") else st.kind for st in s.stages)
        if s.model is not None:
            stages = f"model `{s.model}`; " + stages
        lines.append(f"| `{path.name}` | {s.world} | {stages} | {' '.join(s.description.split())} |")
    return lines + [""]


def reference(folder: Path | None = None) -> str:
    lines = ["# Scenarios", "",
             "Generated from the scenario's definition (`python -m services.scenario.reference scenarios > "
             "docs/scenarios.md`): each key's default and meaning are its field's, in "
             "`services/scenario/model.py` and `stages.py`.", "", INTRO]
    if folder is not None:
        lines += ["## The scenario files", "", *_files(Path(folder))]
    lines += ["## Keys", "", "Every key is optional unless it says required; an unknown key anywhere is an error.",
              "", "### The scenario", "", *_table(_rows(Scenario))]
    cell = _rows(CellSpec)
    cell = [r for r in cell if not r.startswith("| `fri`")]
    cell += [f"| `{FRI_PREFIX}{f.name}` | {_value(f.default)} | {_esc(f.metadata['doc'])} |"
             for f in dataclasses.fields(LinkFaultSpec)]
    lines += ["### `cell`: the simulated cell's physics and devices", "",
              "What a sweep varies.  The `fri_*` keys are the FRI link's faults "
              "(`robot_sim.krc.faults.LinkFaultSpec`; the robot's `--fri-*` flags are the same fields).", "",
              *_table(cell)]
    for kind, cls in STAGE_TYPES.items():
        lines += [f"### `{kind}`", "", " ".join((cls.__doc__ or "").split("\n\n")[0].split()), "",
                  *_table(_rows(cls))]
    lines += ["### World defaults", "", "What a stage takes when it leaves `start` or `goal_x` out, and the cell "
              "its `plate_friction` (from `robot_sim.world.tasks`).", "",
              "| world | start (left side) | goal_x | plate_friction |", "|---|---|---|---|"]
    for world, start in DEFAULT_STARTS.items():
        valley = world == "valley"
        lines.append(f"| {world} | `{list(start)}` | {_value(VALLEY_GOAL_X) if valley else '-'} | "
                     f"{_value(Valley.friction) if valley else '-'} |")
    lines += ["", RULES]
    return "\n".join(lines).rstrip("\n") + "\n"


if __name__ == "__main__":
    sys.stdout.write(reference(Path(sys.argv[1]) if len(sys.argv) > 1 else None))
