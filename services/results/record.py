"""What a run did, as the runner hands it to the report: a typed record, not the runner.

The runner fills one ``RunRecord`` as it walks the stages (each episode's recording,
start and the robot's summary; what the learn stage fitted) and adds what it knows at
the end (the services' statistics, restarts, hosts, the realtime profile's grant);
``services.results.report.write_report`` reads nothing else.  The report leaves in it
what it wrote (report.json's content and report.txt's) and what the figures draw from
each recording, decoded with the report (``services.results.decoding``): the figures
and the page drawn after it read neither the recordings nor the report again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from services.results.decoding import FigureData, LearnerView


@dataclass
class EpisodeRecord:
    """One demonstration or reproduction."""

    path: str  # its recording, as this runner sees it
    side: str
    start: list
    summary: dict  # the robot's episode summary (services.runtime.messages.EPISODE_SUMMARY)
    recording: dict | None = None  # what the recorder said when it closed the file (None: it could not)
    # reproductions: the force that fails it, the model that drove it and that model's phase mapping
    max_contact_force: float | None = None
    model: str | None = None
    phase_to_truth: dict | None = None
    # what the figures draw from its recording, decoded with the report (None: not asked for)
    figure_data: FigureData | None = None


@dataclass
class ModelRecord:
    """One model the learn stage fitted (or the scenario's stored model)."""

    name: str | None  # ETAR or STAR when the learn stage fitted more than one
    path: str
    goal: list
    phase_to_truth: dict | None


@dataclass
class LearningRecord:
    model: ModelRecord | None = None  # the run's model (the first learned, or the scenario's)
    selection: dict | None = None  # how the number of phases was chosen
    learned_from: list = field(default_factory=list)  # dicts: path, samples (what the learn stage read)
    seconds: float | None = None
    # every model the learn stage fitted, by transition model ("effect", "state"): the run's first
    models: dict[str, ModelRecord] = field(default_factory=dict)
    # each model scored against the true phases of the demonstrations (etar.comparison), with more than one
    offline: list = field(default_factory=list)
    # the demonstrations as the learn stage read them (their arrays): the figures', not the report's
    demonstrations: list = field(default_factory=list, repr=False)

    def adopt(self, model: ModelRecord, selection: dict | None) -> None:
        """``model`` is the run's model from now on."""
        self.model, self.selection = model, selection

    # the run's model, as the report names it (None before one is learned or loaded)
    @property
    def model_path(self) -> str | None:
        return None if self.model is None else self.model.path

    @property
    def goal(self) -> list | None:
        return None if self.model is None else self.model.goal

    @property
    def phase_to_truth(self) -> dict | None:
        return None if self.model is None else self.model.phase_to_truth


@dataclass
class RunRecord:
    scenario_name: str
    source: str  # where the scenario came from (a file name)
    clock: str
    run_id: str
    out: Path  # the run's folder, absolute
    transport: str
    engine: str | None = None  # in one process: how the FRI cycles were stepped (per-message, fused)
    # zenoh: FRI and the wrench over the bus; udp: over FRI 1.0/UDP and Net F/T (--wire udp, serve)
    wire: str = "zenoh"
    world: str | None = None  # the task world: its surfaces and its phases' names in the figures
    workers: int | None = None  # processes for reading the recordings (None: one per CPU)
    # the figures are drawn after the report: it decodes their data too, as the learner takes
    # a recording (None: no figures)
    figures: LearnerView | None = None
    demonstrations: list[EpisodeRecord] = field(default_factory=list)
    reproductions: list[EpisodeRecord] = field(default_factory=list)
    learning: LearningRecord = field(default_factory=LearningRecord)
    # etar-bench serve: the episode a lab's own FRI remote drove over UDP
    served: list[EpisodeRecord] = field(default_factory=list)
    # filled in at the end of the run
    service_stats: dict = field(default_factory=dict)  # role -> its last status (links, counters)
    realtime_profile: dict | None = None  # what the profile asked for and was granted, when it asked
    restarts: list = field(default_factory=list)
    hosts: list = field(default_factory=list)
    # what made the run: code version and commit, date, command line, library versions
    # (services.runtime.provenance)
    provenance: dict = field(default_factory=dict)
    report: dict | None = None  # report.json's content, once written
    report_text: str | None = None  # report.txt's, once written
