"""The scenario runner: starts the processes a scenario needs, drives its stages,
stops everything cleanly and writes the recordings, the model and the report.

    etar-bench run scenarios/valley.yaml --out runs/valley

Stages (``services.scenario``):

- demonstrate: per demonstration, the recorder opens a file, the robot is put
  at the start in gravity compensation, the sensor is tared while the arm
  rests, the teacher guides the arm until it is done;
- learn: ETAR is fitted to the recorded MCAP files (BIC over the candidates,
  or a fixed number of phases), and every phase's impedance is derived;
- reproduce: per reproduction, the robot starts where no demonstration did, in
  Cartesian impedance under FRI command mode; the estimator and the commander
  close the loop until the goal is reached (or time runs out; with
  ``stop_at_goal: false`` for the whole time, holding at the goal).

A scenario with a ``model`` file reproduces with that model (learned by an
earlier run, which stored the goal and the phase mapping in its metadata)
instead of learning one.

Everything the report says is measured from the recordings and the services'
own statistics (``services.report``).
"""

from __future__ import annotations

import json
import os
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from etar import ETAR
from etar.impedance import phase_impedances
from etar.selection import fit_order
from services import launch
from services.recording import RecordingError, load_demonstration
from services.runtime import topics
from services.runtime.messages import EPISODE_SUMMARY, RUNNER_EVENT
from services.runtime.service import now_ns, request
from services.runtime.session import ZenohOptions, open_session
from services.scenario import Scenario, demonstration_starts, load_scenario, reproduction_starts

# with isolate_robot: who gets the robot's CPU.  The sensor there too made it worse
# (measured on 2 CPUs: FRI answered in time 57 % instead of 99 %, the sensor as far behind)
ROBOT_CPU_ROLES = ("robot",)

DEMO_TOPICS = ["robot/state", "robot/contact", "ft/wrench", "teacher/wrench"]
REPRO_TOPICS = ["robot/state", "robot/contact", "ft/wrench", "robot/command"]


@dataclass(frozen=True)
class RunOptions:
    scenario: str
    out: str
    clock: str | None = None
    run_id: str | None = None
    zenoh: ZenohOptions | None = None  # None: the runner listens on a free loopback port
    robot_args: tuple = ()  # extra flags for the robot (e.g. fault injection)
    commander_args: tuple = ()
    attach: bool = False  # the services are already running (docker-compose): do not spawn them
    # SCHED_FIFO (where permitted) for the two ends of the FRI link, the robot above the
    # commander; the others stay ordinary processes.  All six at one priority starve
    # one another on two cores (measured: 97 % missed deadlines)
    sched_fifo: bool = False
    fifo_priorities: tuple = (("robot", 60), ("impedance_commander", 55))  # (role, priority) used with sched_fifo
    # the robot (with the sensor, see ROBOT_CPU_ROLES) on the last CPU, every other
    # service on the others: the 1 kHz loop keeps most of a core (and its caches) instead
    # of sharing it with five processes that each wake a thousand times a second
    isolate_robot: bool = False
    ready_timeout: float = 60.0


@dataclass
class RunState:
    demonstrations: list = field(default_factory=list)  # dicts: path, start, side, summary
    reproductions: list = field(default_factory=list)
    model_path: str | None = None
    selection: dict | None = None
    phase_to_truth: dict | None = None
    goal: list | None = None
    learned_from: list = field(default_factory=list)  # dicts: path, samples (what the learn stage read)


class Runner:
    def __init__(self, options: RunOptions, progress=print):
        self.options = options
        self.say = progress
        self.scenario: Scenario = load_scenario(options.scenario)
        if options.clock:
            self.scenario = self.scenario.with_clock(options.clock)
        # resolved once, here: every path handed to a service or written in the report
        # follows from this absolute folder (a relative one, joined again by the
        # recorder, doubled itself: out/valley/recordings/out/valley/recordings/)
        self.out = Path(options.out).expanduser().resolve()
        self.recordings = self.out / "recordings"
        self.run_id = options.run_id or f"{self.scenario.name}-{uuid.uuid4().hex[:8]}"
        source = Path(self.scenario.source)
        self.scenario_text = source.read_text() if source.is_file() else None  # attached to every recording
        self.state = RunState()
        self._episode_done = threading.Event()
        self._summary = None

    # --------------------------------------------------------------- roles

    def roles(self) -> list[str]:
        kinds = {s.kind for s in self.scenario.stages}
        roles = ["robot", "ft_sensor", "recorder"]
        if "demonstrate" in kinds:
            roles.append("teacher")
        if "reproduce" in kinds:
            roles += ["phase_estimator", "impedance_commander"]
        return roles

    def _args(self, role: str, connect: str) -> list[str]:
        sc = self.scenario
        priority = dict(self.options.fifo_priorities).get(role) if self.options.sched_fifo else None
        common = ["--run-id", self.run_id, "--clock", sc.clock] + (["--sched-fifo", str(priority)] if priority else [])
        cpus = os.sched_getaffinity(0)
        if self.options.isolate_robot and len(cpus) >= 2:
            last = max(cpus)
            mine = [last] if role in ROBOT_CPU_ROLES else sorted(cpus - {last})
            common += ["--cpus", ",".join(map(str, mine))]
        if self.options.zenoh is not None:
            common += self.options.zenoh.to_args()
        else:
            common += ["--connect", connect]
        extra = {
            "robot": ["--world", sc.world, "--seed", str(sc.seed), *self.options.robot_args],
            "teacher": ["--world", sc.world],
            "ft_sensor": ["--seed", str(sc.seed)],
            "recorder": ["--out-dir", str(self.recordings)],
            "impedance_commander": list(self.options.commander_args),
        }.get(role, [])
        return common + extra

    # ----------------------------------------------------------------- run

    def run(self) -> dict:
        from services.report import write_report

        self.recordings.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        if self.options.zenoh is not None:
            zopts, endpoint = self.options.zenoh, ""
        else:
            endpoint = f"tcp/127.0.0.1:{launch.free_port()}"
            zopts = ZenohOptions(listen=(endpoint,))
        self.say(f"run {self.run_id}: scenario {self.scenario.name} ({self.scenario.source}), "
                 f"clock {self.scenario.clock}, output {self.out}")
        session = open_session(zopts)
        self.session = session
        self._pub_event = session.declare_publisher(topics.key(self.run_id, "runner/event"))
        sub = session.declare_subscriber(topics.key(self.run_id, "robot/episode"), self._on_episode)
        processes = []
        error = None
        try:
            if not self.options.attach:
                for role in self.roles():
                    processes.append(launch.spawn(role, self._args(role, endpoint), self.out / "logs"))
            launch.wait_alive(session, self.run_id, self.roles(), processes, timeout=self.options.ready_timeout)
            self.say(f"services ready ({', '.join(self.roles())}) after {time.monotonic() - t0:.1f} s")
            if self.scenario.model is not None:
                self._use_model(self.scenario.model_path())
            for stage in self.scenario.stages:
                getattr(self, f"stage_{stage.kind}")(stage)
            self._event("run_end", "", -1, {})
        except BaseException as exc:
            error = f"{type(exc).__name__}: {exc}"
            self.say(f"run failed: {error}")
            for p in processes:
                if not p.alive():
                    self.say(f"--- {p.name} exited with {p.popen.returncode}; end of its log:\n{p.tail()}")
            if isinstance(exc, KeyboardInterrupt):
                raise
        finally:
            self.service_stats = self._collect_stats()
            codes = {}
            if not self.options.attach:
                self._shutdown_services()
                codes = launch.stop(processes)
            try:
                report = write_report(self, codes, error, time.monotonic() - t0)
            finally:
                if self.options.attach:
                    # containers stop with their services: only once the report is written
                    self._shutdown_services()
                sub.undeclare()
                session.close()
        return report

    def _collect_stats(self) -> dict:
        """Each service's own link statistics (receiving end), before they stop."""
        out = {}
        for role in self.roles():
            try:
                out[role] = self._req(role, "status", timeout=3.0)
            except Exception as exc:  # a dead service has no statistics; the report says so
                out[role] = {"error": f"{type(exc).__name__}: {exc}"}
        return out

    def _shutdown_services(self):
        for role in self.roles():
            try:
                request(self.session, self.run_id, role, "shutdown", timeout=2.0)
            except Exception:  # already gone: launch.stop's escalation handles it
                pass

    # ------------------------------------------------------------- helpers

    def _event(self, event, stage, episode, info):
        self._pub_event.put(RUNNER_EVENT.encode(seq=0, stamp_ns=0, sent_ns=now_ns(), event=event, stage=stage,
                                                episode=episode, info=info))

    def _on_episode(self, sample):
        try:
            self._summary = EPISODE_SUMMARY.decode(sample.payload.to_bytes())
        except ValueError:
            return
        self._episode_done.set()

    def _req(self, role, cmd, timeout=30.0, **args):
        return request(self.session, self.run_id, role, cmd, timeout=timeout, **args)

    def _run_episode(self, wait_for, stop_on, max_seconds) -> dict:
        self._episode_done.clear()
        self._req("robot", "run", wait_for=wait_for, stop_on=stop_on, max_seconds=max_seconds)
        # lockstep runs at the pace of the slowest participant: allow a generous wall-clock budget
        if not self._episode_done.wait(max(120.0, 30.0 * max_seconds)):
            self._req("robot", "stop", timeout=10.0)
            if not self._episode_done.wait(30.0):
                raise TimeoutError("the robot did not end its episode")
        return self._summary

    def _prepare(self, kind, index, start) -> Path:
        """Open the episode's recording and put the arm at its start; returns the
        recording's path as this runner sees it."""
        name = f"{kind}_{index:02d}.mcap"
        # the recorder is told the name relative to its --out-dir, the one folder both
        # agree on: OUT/recordings (spawned), or a shared volume (--attach)
        written = self._req("recorder", "begin_episode", path=name, kind=kind, index=index,
                            scenario=self.scenario_text,
                            metadata={"start": json.dumps(list(start)), "scenario": self.scenario.name})["path"]
        self._event("episode_begin", kind, index, {"start": list(start)})
        self._req("robot", "reset", start=list(start), episode=index, kind=kind)
        self._req("ft_sensor", "tare", samples=100)
        self._req("robot", "settle", cycles=200, wait_for=["ft"] if self.scenario.clock == "lockstep" else [],
                  timeout=120.0)
        path = self.recordings / name
        if self.options.attach and not path.exists():
            raise RecordingError(f"the recorder writes {written}, which this runner does not see at {path}: "
                                 f"with --attach the recorder's --out-dir must be this run's --out/recordings "
                                 f"(the same folder, e.g. a shared volume)")
        return path

    def _finish(self, kind, index, summary, topic_list):
        rec = self._req("recorder", "end_episode", last_seq=summary["last_seq"], topics=topic_list, timeout=30.0)
        self._event("episode_end", kind, index, {"reason": summary["reason"]})
        return rec

    # -------------------------------------------------------------- stages

    def stage_demonstrate(self, stage):
        sc = self.scenario
        starts = demonstration_starts(stage, sc.world, stage.seed)
        for i, (side, start) in enumerate(starts):
            index = len(self.state.demonstrations)
            path = self._prepare("demonstration", index, start)
            reset = dict(start=list(start), episode=index, seed=stage.seed * 1000 + i)
            if stage.goal_x is not None:
                reset["goal_x"] = stage.goal_x
            self._req("teacher", "reset", **reset)
            wait = ["teacher"] if sc.clock == "lockstep" else []
            summary = self._run_episode(wait, "teacher_done", stage.max_seconds)
            rec = self._finish("demonstration", index, summary, DEMO_TOPICS)
            self.state.demonstrations.append(dict(path=str(path), side=side, start=list(start), summary=summary,
                                                  recording=rec))
            self.say(f"demonstration {index + 1}/{len(starts)} ({side}): {summary['reason']} after "
                     f"{summary['sim_seconds']:.1f} s simulated / {summary['wall_seconds']:.1f} s wall, "
                     f"{rec['messages']} messages recorded")

    def stage_learn(self, stage):
        sc = self.scenario
        demos = [load_demonstration(d["path"], state=sc.state, features=sc.features)
                 for d in self.state.demonstrations]
        pairs = [(d["states"], d["forces"]) for d in demos]
        self.state.learned_from = [dict(path=d["path"], samples=len(s)) for d, (s, _) in
                                   zip(self.state.demonstrations, pairs)]
        options = dict(n_restarts=stage.restarts)
        t = time.monotonic()
        if stage.phases == "auto":
            self.say(f"learning: {stage.criterion.upper()} over {list(stage.candidates)} phases from "
                     f"{len(pairs)} demonstrations ({sum(len(s) for s, _ in pairs)} samples)")
            model, self.state.selection = fit_order(pairs, stage.candidates, stage.criterion, stage.selection,
                                                    transitions=stage.transitions, seed=stage.seed,
                                                    max_iter=stage.max_iter, progress=self.say, **options)
        else:
            model = ETAR(int(stage.phases), stage.transitions, **options).fit(
                pairs, max_iter=stage.max_iter, seed=stage.seed)
            self.state.selection = dict(criterion="fixed", best=int(stage.phases), scores={}, log_likelihoods={
                str(stage.phases): model.fit_report_.log_likelihood}, n_parameters={})
        dt = float(demos[0]["dt"])
        pose = sc.state == "pose"  # the state's columns 3:6 are the orientation (services.features)
        imps = phase_impedances(model, pairs, dt, rotation_columns=slice(3, 6) if pose else None)
        model.metadata.update(impedance=[None if i is None else i.to_dict() for i in imps], dt=dt,
                              state=sc.state, features=sc.features,
                              demonstrations=[d["path"] for d in self.state.demonstrations],
                              selection=self.state.selection)
        # which learned phase is which true phase, judged on the demonstrations only
        from etar.metrics import match_phases

        truth = np.concatenate([d["phases"] for d in demos])
        pred = np.concatenate([model.viterbi(s, f) for s, f in pairs])
        self.state.phase_to_truth = match_phases(truth, pred, n_pred=model.n_phases)
        self.state.goal = np.mean([s[-1][:3] for s, _ in pairs], axis=0).tolist()
        # a later scenario can reproduce with this file alone (its `model` key)
        if pose:
            # the demonstrations' mean final turn, relative to each one's first orientation
            model.metadata.update(goal_rotation=np.mean([s[-1][3:6] for s, _ in pairs], axis=0).tolist())
        model.metadata.update(goal=self.state.goal,
                              phase_to_truth={str(k): int(v) for k, v in self.state.phase_to_truth.items()})
        path = self.out / "model.json"
        model.save(path)
        self.state.model_path = str(path)
        self.say(f"learned {model.n_phases} phases in {time.monotonic() - t:.1f} s; model {path}")

    def _use_model(self, path: Path) -> None:
        model = ETAR.load(path)
        meta = model.metadata
        if not meta.get("impedance") or meta.get("goal") is None:
            raise ValueError(f"{path}: the model has no per-phase impedance or goal in its metadata; "
                             f"use a model.json written by a run's learn stage")
        self.state.model_path = str(Path(path).resolve())
        self.state.goal = list(meta["goal"])
        self.state.phase_to_truth = {int(k): int(v) for k, v in (meta.get("phase_to_truth") or {}).items()} or None
        self.state.selection = meta.get("selection")
        self.say(f"model {path}: {model.n_phases} phases, goal {np.round(self.state.goal, 3).tolist()}")

    def stage_reproduce(self, stage):
        sc = self.scenario
        if self.state.model_path is None:
            raise RuntimeError("reproduce needs a learned model")
        demo_starts = [(d["side"], tuple(d["start"])) for d in self.state.demonstrations]
        starts = reproduction_starts(stage, sc.world, stage.seed, demo_starts)
        model_path = str(Path(self.state.model_path).resolve())
        for i, (side, start) in enumerate(starts):
            index = len(self.state.reproductions)
            path = self._prepare("reproduction", index, start)
            self._req("phase_estimator", "reset", model=model_path, episode=index, state=sc.state,
                      features=sc.features)
            goal = list(self.state.goal)
            self._req("impedance_commander", "reset", model=model_path, episode=index, goal=goal,
                      goal_tolerance=stage.goal_tolerance)
            wait = ["command"] if sc.clock == "lockstep" else []
            summary = self._run_episode(wait, "goal_reached" if stage.stop_at_goal else None, stage.max_seconds)
            rec = self._finish("reproduction", index, summary, REPRO_TOPICS)
            self.state.reproductions.append(dict(path=str(path), side=side, start=list(start), summary=summary,
                                                 recording=rec, max_contact_force=stage.max_contact_force))
            self.say(f"reproduction {index + 1}/{len(starts)} ({side}): {summary['reason']}, peak contact "
                     f"{summary['peak_contact_force']:.1f} N, {summary['sim_seconds']:.1f} s simulated / "
                     f"{summary['wall_seconds']:.1f} s wall")


def run(options: RunOptions, progress=print) -> dict:
    return Runner(options, progress).run()
