"""What the tests share: the repository's scenarios as values, a run of one, and the
processes of a run."""

from __future__ import annotations

import os
from pathlib import Path

from services.run.options import RunOptions
from services.run.runner import Runner
from services.scenario import Scenario, load_scenario
from services.transport.launch import PROGRAM_MODULE

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
SMOKE_MODEL = str(SCENARIOS / "models" / "smoke.json")  # learned by the smoke scenario, stored


def scenario(name: str, changes: dict | None = None) -> Scenario:
    """``scenarios/<name>.yaml`` as a value, with ``changes`` ({path: value}, as
    ``Scenario.replace`` takes them) applied in order."""
    value = load_scenario(SCENARIOS / f"{name}.yaml")
    for path, new in (changes or {}).items():
        value = value.replace(path, new)
    return value


def hold(seconds: float, changes: dict | None = None) -> Scenario:
    """``scenarios/hold.yaml`` (the smoke reproduction held at its goal with the stored
    model, realtime) cut to ``seconds``."""
    return scenario("hold", {"reproduce.max_seconds": seconds, **(changes or {})})


def runner(value: Scenario, out, progress=print, **options) -> Runner:
    """A runner of ``value`` into ``out``; ``options`` as ``RunOptions`` takes them (no
    figures unless asked: most tests do not look at them)."""
    return Runner(value, RunOptions(out=str(out), **{"figures": False, **options}), progress)


def run(value: Scenario, out, progress=print, **options) -> dict:
    """``value`` run to its end: its report."""
    return runner(value, out, progress, **options).run()


def service_pid(role: str, run_id: str) -> int | None:
    """The pid of ``role``'s process in run ``run_id`` (``python -m services.cli.roles ROLE --run-id ...``)."""
    program = [PROGRAM_MODULE.encode(), role.encode()]
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        at = argv.index(program[0]) if program[0] in argv else -1
        if at >= 0 and argv[at:at + 2] == program and run_id.encode() in argv:
            return int(pid)
    return None
