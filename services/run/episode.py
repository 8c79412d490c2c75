"""The episode protocol, written once: open the episode's recording, put the arm at its start,
tare the sensor while the arm rests, settle; hand the episode to its drivers (the teacher,
or the estimator and the commander); run the FRI cycles; close the recording.  The runner,
the benches and the tests drive episodes through ``Episodes``.

A service lost during an episode (its process died, or it stopped answering) ends the
episode: the robot's summary is kept as a failed episode, the recording is closed with
what arrived, and ``raise_if_lost`` then ends the run with the error.  A service with a
restart policy that comes back rejoins the episode in progress (``rejoin``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from services.recordings.format import RecordingError
from services.recordings.reader import recording_gaps
from services.run.progress import EpisodeProgress
from services.runtime.cycle import LOCKSTEP_GIVE_UP
from services.runtime.messages import (FT_WRENCH, ROBOT_COMMAND, ROBOT_CONTACT, ROBOT_STATE, RUNNER_EVENT,
                                       TEACHER_WRENCH)
from services.runtime.roles import PARTICIPANTS
from services.transport.cell import Cell, ServiceLost
from services.transport.subscriptions import now_ns

# what the recorder waits for before it closes an episode's file
DEMONSTRATION_TOPICS = (ROBOT_STATE.topic, ROBOT_CONTACT.topic, FT_WRENCH.topic, TEACHER_WRENCH.topic)
REPRODUCTION_TOPICS = (ROBOT_STATE.topic, ROBOT_CONTACT.topic, FT_WRENCH.topic, ROBOT_COMMAND.topic)
SETTLE_CYCLES = 200  # the arm at rest before an episode, the sensor tared over its last ...
TARE_SAMPLES = 100
SETTLE_TIMEOUT_S = 120.0


@dataclass
class Recording:
    """Where an episode's recording goes: the recorder's folder as this process sees it,
    the scenario every file attaches and the metadata every file carries."""

    folder: Path
    scenario_text: str | None
    scenario_name: str
    attached: bool = False  # the recorder was started by someone else (--attach): it must see ``folder`` too


class Episodes:
    """Episodes on a cell.  ``clock``: the scenario's (in lockstep the arm settles with the
    sensor's answers); ``recording``: None records nothing (benches); ``roles``: the run's
    services (to find one that went silent)."""

    def __init__(self, cell: Cell, *, clock: str = "lockstep", recording: Recording | None = None, roles=()):
        self.cell = cell
        self.clock = clock
        self.recording = recording
        self.roles = list(roles)
        self.lost: ServiceLost | None = None  # a service that disappeared during an episode
        # what a restarted service rejoins: the episode in progress, its recording's further
        # parts, its metadata, the estimator's reset
        self._episode = None
        self._parts: list[Path] = []
        self._metadata: dict = {}
        self._estimator_reset = None

    # ------------------------------------------------------------------ episodes

    def demonstrate(self, index: int, start, *, seed: int, goal_x: float | None, max_seconds: float,
                    label: str = "demonstration") -> tuple[dict, dict | None, Path | None]:
        """One demonstration by the teacher: (the robot's summary, what the recorder said,
        the recording's path)."""
        path = self.begin("demonstration", index, start)
        reset = dict(start=list(start), episode=index, seed=seed)
        if goal_x is not None:
            reset["goal_x"] = goal_x
        said = self.request("teacher", "reset", **reset)
        summary = self.run(["teacher"], "teacher_done", max_seconds, label=label,
                           listening=[said["listening"]] if said.get("listening") else [])
        if self.lost is None:
            self.request("teacher", "idle")
        return summary, self.finish("demonstration", index, summary, DEMONSTRATION_TOPICS), path

    def reproduce(self, index: int, start, *, model: str, goal=None, goal_tolerance: float | None = None,
                  stop_at_goal: bool = True, max_seconds: float,
                  label: str = "reproduction") -> tuple[dict, dict | None, Path | None]:
        """One reproduction with the model file ``model``: (summary, recorder's word, path).
        ``goal``/``goal_tolerance``: None leaves the commander's (the model's goal)."""
        path = self.begin("reproduction", index, start, model=model)
        self._estimator_reset = dict(model=model, episode=index)
        self.request("phase_estimator", "reset", **self._estimator_reset)
        commander = dict(model=model, episode=index)
        if goal is not None:
            commander["goal"] = list(goal)
        if goal_tolerance is not None:
            commander["goal_tolerance"] = goal_tolerance
        self.request("impedance_commander", "reset", **commander)
        summary = self.run(["command"], "goal_reached" if stop_at_goal else None, max_seconds, label=label)
        return summary, self.finish("reproduction", index, summary, REPRODUCTION_TOPICS), path

    # ------------------------------------------------------------------ the steps

    def begin(self, kind: str, index: int, start, model: str | None = None) -> Path | None:
        """Open the episode's recording and put the arm at its start, at rest, the sensor
        tared; the recording's path as this process sees it (None: not recorded).
        ``model``: the model file a reproduction runs (in the recording's metadata: what
        its visual topics draw the stiffness of)."""
        name = f"{kind}_{index:02d}.mcap"
        self._episode, self._parts = (kind, index), []
        path = None
        if self.recording is not None:
            self._metadata = {"start": json.dumps(list(start)), "scenario": self.recording.scenario_name}
            if model is not None:
                self._metadata["model"] = model
            # the recorder is told the name relative to its --out-dir, the one folder both
            # agree on: OUT/recordings (spawned), or a shared volume (--attach)
            written = self.request("recorder", "begin_episode", path=name, kind=kind, index=index,
                                   scenario=self.recording.scenario_text, metadata=self._metadata)["path"]
            self.event("episode_begin", kind, index, {"start": list(start), **({"model": model} if model else {})})
            path = self.recording.folder / name
        self.request("robot", "reset", start=list(start), episode=index, kind=kind)
        self.request("ft_sensor", "tare", samples=TARE_SAMPLES)
        # realtime: the robot subscribes to what it applies only, so it does not wait for the sensor
        self.request("robot", "settle", cycles=SETTLE_CYCLES, wait_for=["ft"] if self.clock == "lockstep" else [],
                     timeout=SETTLE_TIMEOUT_S)
        if path is not None and self.recording.attached and not path.exists():
            raise RecordingError(f"the recorder writes {written}, which this runner does not see at {path}: "
                                 f"with --attach the recorder's --out-dir must be this run's --out/recordings "
                                 f"(the same folder, e.g. a shared volume)")
        return path

    def run(self, answers_from, stop_on, max_seconds: float, label: str = "episode", listening=()) -> dict:
        """One episode of cycles (the robot's 'run'); returns the robot's summary.  In
        lockstep each cycle waits for ``answers_from`` and the sensor (while it records:
        ``services.runtime.cycle.IN_STEP_ONLY``); in realtime a cycle closes as soon
        as they have answered, or at its deadline.  On a terminal a bar shows its simulated
        time and real-time factor."""
        bar = EpisodeProgress(label, max_seconds)
        if self.clock == "lockstep" and answers_from and "ft" not in answers_from:
            # and the sensor's record of it: a cycle run ahead of the sensor let a foreign peer's
            # copy of a later robot/contact reach it before the real ones, which it then dropped
            # as older; its noise drew for other cycles and the run's results changed
            answers_from = [*answers_from, "ft"]
        try:
            summary = self.cell.run_episode(answers_from, stop_on, max_seconds,
                                            progress=bar.update if bar.enabled else None, listening=listening)
            if summary["reason"].startswith("unanswered:"):
                # lockstep: alive but silent (stopped, hung, cut off); the robot gave up on it.
                # The one that went silent may be further up the chain (the commander waits
                # for the estimator): whoever does not answer a status request is the one
                silent = [PARTICIPANTS.get(p, p) for p in summary["reason"].split(":", 1)[1].split(",")]
                stuck = self.cell.unresponsive(self.roles)
                who = stuck or silent
                self.lost = ServiceLost(
                    who[0], f"service {', '.join(who)} stopped answering"
                            f"{' (alive, no reply to a status request in 1 s)' if stuck else ''}: the robot's cycle "
                            f"{summary['last_seq']} ({summary['sim_seconds']:.3f} s simulated) and the one before went "
                            f"unanswered by {', '.join(silent)} for {LOCKSTEP_GIVE_UP} x the answer timeout, and "
                            f"the robot ended the episode", summary)
            return summary
        except ServiceLost as exc:
            if exc.summary is None:
                raise
            # the robot stopped the episode when the service went: keep what it measured,
            # as a failed episode, then end the run (raise_if_lost) with the error
            self.lost = exc
            return dict(exc.summary, reason=f"lost:{exc.role}")
        finally:
            bar.close()

    def finish(self, kind: str, index: int, summary: dict, topics) -> dict | None:
        """The recorder closes the episode's file; with a service lost, whatever it can
        (None if the recorder is the one lost: the robot's summary is kept anyway)."""
        rec = None
        if self.recording is not None:
            if self.lost is not None:
                topics = []  # what a lost service would have sent is not coming: do not wait for it
            try:
                rec = self.request("recorder", "end_episode", last_seq=summary["last_seq"], topics=list(topics),
                                   timeout=30.0)
            except (ServiceLost, TimeoutError, RuntimeError):
                if self.lost is None:
                    raise
            if self.lost is None:
                self.event("episode_end", kind, index, {"reason": summary["reason"]})
            if self._parts:
                # the recorder was restarted during the episode: its first file ends where the
                # killed one stopped writing; say which cycles no part holds
                first = self.recording.folder / f"{kind}_{index:02d}.mcap"
                rec = dict(rec or {}, parts=[str(p) for p in self._parts],
                           gaps=recording_gaps([first, *self._parts]))
        self._episode, self._parts, self._estimator_reset = None, [], None
        return rec

    def raise_if_lost(self) -> None:
        if self.lost is not None:
            raise self.lost

    def rejoin(self, role: str) -> None:
        """A service with a restart policy is back: it rejoins the episode in progress.
        The recorder writes on in a further part of the episode's recording (the gap is
        reported); the estimator's filter starts again where the reproduction is."""
        if self._episode is None:
            return
        kind, index = self._episode
        if role == "recorder" and self.recording is not None:
            name = f"{kind}_{index:02d}.part{len(self._parts) + 2}.mcap"
            self.request("recorder", "begin_episode", path=name, kind=kind, index=index,
                         scenario=self.recording.scenario_text,
                         metadata=dict(self._metadata, part=str(len(self._parts) + 2)))
            self._parts.append(self.recording.folder / name)
        elif role == "phase_estimator" and self._estimator_reset is not None:
            self.request("phase_estimator", "reset", resync=True, **self._estimator_reset)

    # ------------------------------------------------------------------ helpers

    def event(self, event: str, stage: str, episode: int, info: dict) -> None:
        """A runner event (``runner/event``): recorded, and drawn in the log of the visual topics."""
        self.cell.publish(RUNNER_EVENT.topic, RUNNER_EVENT.encode(
            seq=0, stamp_ns=0, sent_ns=now_ns(), event=event, stage=stage, episode=episode, info=info))

    def request(self, role: str, cmd: str, timeout: float = 30.0, **args) -> dict:
        return self.cell.request(role, cmd, timeout=timeout, **args)
