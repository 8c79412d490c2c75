"""The testbench's services: the nodes, how they are carried, how a scenario is run
and what a run leaves (docs/architecture.md).  For notebooks:

    from services import run_scenario, recording_arrays, topic_arrays

loaded on first use, so that a service's process (``python -m services.cli.roles``)
does not load the runner."""

__all__ = ["run_scenario", "load_scenario", "Scenario", "recording_arrays", "topic_arrays", "topic_frame"]

_HOMES = {"run_scenario": "services.run.api", "load_scenario": "services.scenario", "Scenario": "services.scenario",
          "recording_arrays": "services.recordings.arrays", "topic_arrays": "services.recordings.arrays",
          "topic_frame": "services.recordings.arrays"}


def __getattr__(name: str):
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'services' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(home), name)
