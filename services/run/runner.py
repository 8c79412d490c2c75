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
own statistics (``services.results.report``).
"""

from __future__ import annotations

import functools
import json
import os
import signal
import threading
import time
import uuid
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from etar import ETAR
from etar.comparison import MODEL_NAMES
from etar.selection import fit_order
from etar.task import LearnedTask, TaskError, learn_task, load_task
from services.transport import launch
from services.transport.hosts import ZENOH_CFG as HOSTS_ZENOH_CFG, Hosts, parse_layout
from services.nodes import (CommanderConfig, EstimatorConfig, FoxgloveBridgeConfig, FtSensorConfig, RecorderConfig,
                            RobotConfig,
                            TeacherConfig)
from services.run.progress import EpisodeProgress
from services.run.realtime_profile import Grant, parse_profile, probe
from services.runtime.roles import FIFO_CHAIN, PARTICIPANTS
from services.recordings.format import RecordingError
from services.recordings.demonstrations import load_demonstration
from services.recordings.reader import recording_gaps
from services.runtime.config import config_to_args, with_flags
from services.runtime.cycle import LOCKSTEP_GIVE_UP
from services.transport.inproc import InProcessCell
from services.runtime.messages import RUNNER_EVENT
from services.transport.credentials import client_options, router_options
from services.transport.service import now_ns
from services.transport.session import ZenohOptions
from services.runtime.threads import learning_threads, process_map
from services.scenario.model import Scenario
from services.scenario.checks import ScenarioError
from services.scenario.starts import demonstration_starts, reproduction_starts
from services.scenario.loading import load_scenario

# with isolate_robot: who gets the robot's CPU.  The sensor there too made it worse
# (measured on 2 CPUs: FRI answered in time 57 % instead of 99 %, the sensor as far behind)
ROBOT_CPU_ROLES = ("robot",)

# the cycle engine's participants and the roles that answer for them
DEMO_TOPICS = ["robot/state", "robot/contact", "ft/wrench", "teacher/wrench"]
REPRO_TOPICS = ["robot/state", "robot/contact", "ft/wrench", "robot/command"]
TRANSPORTS = ("zenoh", "inproc")


@dataclass(frozen=True)
class RunOptions:
    scenario: str
    out: str
    clock: str | None = None
    run_id: str | None = None
    # zenoh: every node in its own process (the lab's layout, realtime or lockstep);
    # inproc: every node in this process on an in-memory bus (lockstep only: speed, sweeps)
    transport: str = "zenoh"
    zenoh: ZenohOptions | None = None  # None: the runner listens on a free loopback port
    robot_args: tuple = ()  # extra flags for the robot (e.g. fault injection)
    commander_args: tuple = ()
    sensor_args: tuple = ()  # extra flags for the ft_sensor (e.g. --fault saturate)
    recorder_args: tuple = ()  # extra flags for the recorder (e.g. --visual-rate-hz 0)
    # the run's credentials (etar-bench certs DIR): the runner is the run's router, mutual
    # TLS only, and only the run's roles may use its keys (services.transport.credentials)
    tls: str | None = None
    # the services on hosts in network namespaces (services.transport.hosts), roles by host:
    # 'robot,ft_sensor:phase_estimator,impedance_commander:recorder,teacher'
    hosts: str | None = None
    # the thesis' figures (RUN_DIR/figures/) and report.html after the report; a sweep's
    # runs leave them out (their table and plots are the sweep's)
    figures: bool = True
    # the visual topics live over Foxglove's WebSocket protocol on this port (services.nodes.
    # foxglove_bridge, one more service); None: no live view (recordings have them regardless)
    foxglove: int | None = None
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
    learn_threads: int | None = None  # numba threads for learning; None: the CPUs this process may use
    # processes for the run's own independent work (the candidate fits of a phase-count
    # selection, reading the recordings for the report); None: one per CPU; a sweep gives 1
    workers: int | None = None
    # with the realtime clock: what to ask of the machine (services.run.realtime_profile);
    # sched_fifo / isolate_robot above add to it with their own priorities
    realtime_profile: str = "auto"

    def __post_init__(self):
        if self.transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {TRANSPORTS}, got {self.transport!r}")
        parse_profile(self.realtime_profile)
        if self.foxglove is not None:
            if not (0 <= self.foxglove <= 65535):
                raise ValueError(f"--foxglove PORT must be in 0..65535 (0: any free port), got {self.foxglove}")
            if self.tls is not None or self.hosts is not None or self.attach:
                raise ValueError("--foxglove cannot be combined with --tls, --hosts or --attach yet: the bridge "
                                 "would need credentials and a host of its own")


@dataclass
class RunState:
    demonstrations: list = field(default_factory=list)  # dicts: path, start, side, summary
    reproductions: list = field(default_factory=list)
    model_path: str | None = None
    selection: dict | None = None
    phase_to_truth: dict | None = None
    goal: list | None = None
    learned_from: list = field(default_factory=list)  # dicts: path, samples (what the learn stage read)
    learn_seconds: float | None = None
    # every model the learn stage fitted, by transition model ("effect", "state"): the
    # run's model first; dicts: name (ETAR/STAR), path, goal, phase_to_truth
    models: dict = field(default_factory=dict)
    # each model scored against the true phases of the demonstrations (etar.comparison),
    # when the learn stage fitted more than one
    offline: list = field(default_factory=list)


class Runner:
    def __init__(self, options: RunOptions, progress=print):
        self.options = options
        self.say = progress
        self.scenario: Scenario = load_scenario(options.scenario)
        if options.clock:
            self.scenario = self.scenario.with_clock(options.clock)
        if options.transport == "inproc" and self.scenario.clock != "lockstep":
            raise ScenarioError("the in-process transport runs lockstep only; use --transport zenoh for realtime",
                                path="clock", value=self.scenario.clock, source=self.scenario.source)
        if options.transport == "inproc" and options.attach:
            raise ValueError("--attach drives services over Zenoh; it cannot be combined with --transport inproc")
        self.hosts = None
        if options.hosts is not None:
            if options.transport == "inproc" or options.zenoh is not None or options.attach:
                raise ValueError("--hosts starts the services on hosts of this machine over Zenoh: it cannot be "
                                 "combined with --transport inproc, --connect or --attach")
            self.hosts = Hosts(parse_layout(options.hosts, self.roles()))
        if options.foxglove:
            _check_port_free(options.foxglove)
        if options.tls is not None:
            if options.transport == "inproc" or options.zenoh is not None or options.attach:
                raise ValueError("--tls makes the runner the run's router over Zenoh: it cannot be combined with "
                                 "--transport inproc, --connect or --attach")
            # every credential checked before anything starts (CredentialsError names the file)
            router_options(options.tls, "check", "tls/127.0.0.1:1")
            for role in self.roles():
                client_options(options.tls, role, "tls/127.0.0.1:1")
        # resolved once, here: every path handed to a service or written in the report
        # follows from this absolute folder (a relative one, joined again by the
        # recorder, doubled itself: out/valley/recordings/out/valley/recordings/)
        self.out = Path(options.out).expanduser().resolve()
        self.recordings = self.out / "recordings"
        self.run_id = options.run_id or f"{self.scenario.name}-{uuid.uuid4().hex[:8]}"
        source = Path(self.scenario.source)
        self.scenario_text = source.read_text() if source.is_file() else None  # attached to every recording
        self.state = RunState()
        self.cell = None
        self.service_stats = {}
        self._lost = None  # launch.ServiceLost, once a service disappeared during an episode
        # what a restarted service rejoins (scenario 'restart:'): the episode in progress,
        # its recording's further parts, the estimator's reset
        self._episode = None
        self._parts: list = []
        self._estimator_reset = None
        realtime = self.scenario.clock == "realtime" and options.transport == "zenoh"
        self.profile = Grant(parse_profile(options.realtime_profile) if realtime else frozenset())

    # --------------------------------------------------------------- roles

    def roles(self) -> list[str]:
        kinds = {s.kind for s in self.scenario.stages}
        roles = ["robot", "ft_sensor", "recorder"]
        if "demonstrate" in kinds:
            roles.append("teacher")
        if "reproduce" in kinds:
            roles += ["phase_estimator", "impedance_commander"]
        if self.options.foxglove is not None:
            roles.append("foxglove_bridge")
        return roles

    def node_configs(self) -> dict:
        """Each role's node config, from the scenario (and the options' extra flags)."""
        sc, cell = self.scenario, self.scenario.cell
        configs = {
            "robot": RobotConfig(world=sc.world, seed=sc.seed, plate_friction=cell.plate_friction,
                                 fri_packet_loss=cell.fri_packet_loss, fri_delay_ms=cell.fri_delay_ms,
                                 fri_jitter_ms=cell.fri_jitter_ms, fri_corruption=cell.fri_corruption,
                                 fri_duplication=cell.fri_duplication, fri_reordering=cell.fri_reordering,
                                 fri_faults_from_s=cell.fri_faults_from_s,
                                 fri_faults_until_s=cell.fri_faults_until_s),
            "ft_sensor": FtSensorConfig(seed=sc.seed, noise_scale=cell.sensor_noise),
            "teacher": TeacherConfig(world=sc.world),
            # in one process the recording's MCAP writing goes to a helper process: it took a fifth of each cycle
            "recorder": RecorderConfig(out_dir=str(self.recordings),
                                       writer_process=self.options.transport == "inproc"),
            "phase_estimator": EstimatorConfig(),
            "impedance_commander": CommanderConfig(),
            "foxglove_bridge": FoxgloveBridgeConfig(world=sc.world, port=self.options.foxglove or 0),
        }
        configs["robot"] = with_flags(configs["robot"], self.options.robot_args)
        configs["impedance_commander"] = with_flags(configs["impedance_commander"], self.options.commander_args)
        configs["ft_sensor"] = with_flags(configs["ft_sensor"], self.options.sensor_args)
        configs["recorder"] = with_flags(configs["recorder"], self.options.recorder_args)
        return {role: configs[role] for role in self.roles()}

    def process_args(self, role: str, config, connect: str) -> list[str]:
        """The command-line flags of ``role``'s process (``services.transport.process``)."""
        sc = self.scenario
        if self.options.sched_fifo:
            priority = dict(self.options.fifo_priorities).get(role)
        else:
            priority = dict(FIFO_CHAIN).get(role) if "fifo" in self.profile.granted else None
        common = ["--run-id", self.run_id, "--clock", sc.clock] + (["--sched-fifo", str(priority)] if priority else [])
        cpus = os.sched_getaffinity(0)
        if (self.options.isolate_robot or "isolate" in self.profile.granted) and len(cpus) >= 2:
            last = max(cpus)
            mine = [last] if role in ROBOT_CPU_ROLES else sorted(cpus - {last})
            common += ["--cpus", ",".join(map(str, mine))]
        if self.options.zenoh is not None:
            common += self.options.zenoh.to_args()
        elif self.options.tls is not None or self.hosts is not None:
            # a client of the runner's router (peers listening on loopback cannot reach
            # one another across hosts), with the router's short lease on a host
            zo = (client_options(self.options.tls, role, connect) if self.options.tls is not None
                  else ZenohOptions(mode="client", connect=(connect,), listen=()))
            if self.hosts is not None:
                zo = replace(zo, cfg=zo.cfg + HOSTS_ZENOH_CFG)
            common += zo.to_args()
        else:
            common += ["--connect", connect]
        return common + config_to_args(config)

    # ----------------------------------------------------------------- run

    def run(self) -> dict:
        from services.results.report import write_report

        self.recordings.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        self.say(f"run {self.run_id}: scenario {self.scenario.name} ({self.scenario.source}), "
                 f"clock {self.scenario.clock}, transport {self.options.transport}, output {self.out}")
        error = None
        codes = {}
        try:
            if self.scenario.model is not None:
                self._use_model(self.scenario.model_path())  # a bad model fails before anything starts
            configs = self.node_configs()
            self._apply_profile()
            if self.options.transport == "inproc":
                self.cell = InProcessCell(self.run_id, configs)
            else:
                if self.hosts is not None:
                    self.hosts.up()
                    self.say("hosts: " + "; ".join(f"{h.describe()}: {', '.join(h.roles)}" for h in self.hosts.hosts))
                self.cell = launch.ServiceProcesses(self.run_id, self.out / "logs", attach=self.options.attach,
                                                    zenoh=self.options.zenoh, tls=self.options.tls, hosts=self.hosts)
                self.cell.restartable = {role for role, policy in self.scenario.restart if policy == "on_failure"}
                if self.options.foxglove is not None:
                    # a view of the run: losing it must not cost the run; it comes back (same port)
                    self.cell.restartable.add("foxglove_bridge")
                self.cell.on_restart = self._on_restart
                self.cell.start(configs, lambda role, connect: self.process_args(role, configs[role], connect),
                                timeout=self.options.ready_timeout)
            self.say(f"services ready ({', '.join(self.roles())}) after {time.monotonic() - t0:.1f} s")
            if self.options.foxglove is not None:
                port = self.cell.request("foxglove_bridge", "status").get("port")
                self.say(f"live view: connect Foxglove to ws://127.0.0.1:{port} (docs/foxglove/README.md)")
            for stage in self.scenario.stages:
                getattr(self, f"stage_{stage.kind}")(stage)
            self._event("run_end", "", -1, {})
        except BaseException as exc:
            if isinstance(exc, KeyboardInterrupt):
                self._escalate_on_next_interrupt()
            error = f"{type(exc).__name__}: {exc}"
            self.say(f"run failed: {error}")
            if self.cell is not None:
                for line in self.cell.post_mortem():
                    self.say(line)
            if isinstance(exc, KeyboardInterrupt):
                raise
        finally:
            if self.cell is not None:
                self.service_stats = self.cell.statistics(self.roles())
                codes = self.cell.stop(self.roles(), before_report=True)
            self.profile.release()
            try:
                report = write_report(self, codes, error, time.monotonic() - t0)
                if self.options.figures:
                    self._figures()
            finally:
                if self.cell is not None:
                    self.cell.stop(self.roles(), before_report=False)
                if self.hosts is not None:
                    self.hosts.down()
        return report

    def _figures(self) -> None:
        """The thesis' figures and the HTML report; a figure that cannot be drawn must not
        cost the run its report (the reason goes in figures.error)."""
        from services.results.figures import write_figures
        from services.results.html import write_html

        t = time.monotonic()
        try:
            written, skipped = write_figures(self.out)
        except Exception as exc:
            (self.out / "figures.error").write_text(f"{type(exc).__name__}: {exc}\n")
            written, skipped = [], [f"{type(exc).__name__}: {exc}"]
        if skipped:
            (self.out / "figures.skipped").write_text("".join(f"{why}\n" for why in skipped))
        try:
            write_html(self.out)
        except Exception as exc:
            (self.out / "report.html.error").write_text(f"{type(exc).__name__}: {exc}\n")
        self.say(f"figures: {len(written)} in {self.out / 'figures'}, report.html "
                 f"({time.monotonic() - t:.1f} s)")

    def _escalate_on_next_interrupt(self) -> None:
        """Interrupted once: the services are being stopped and the report written.  A
        second Ctrl-C (or SIGTERM) must not abort that half-way (leaving orphans and no
        report): it kills the services at once and lets the clean-up finish."""
        if threading.current_thread() is not threading.main_thread():
            return

        def escalate(signum, frame):
            processes = getattr(self.cell, "processes", [])
            self.say(f"{signal.Signals(signum).name} again: killing the {len(processes)} service processes now")
            for p in processes:
                try:
                    os.killpg(p.popen.pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass

        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, escalate)

    def _apply_profile(self) -> None:
        """Find out what the realtime profile is granted, before any service starts, and
        say in one line what a refusal will cost."""
        if not self.profile.requested:
            return
        if self.options.attach:
            self.profile.refused = {p: "the services were started by someone else (--attach)"
                                    for p in sorted(self.profile.requested)}
        else:
            self.profile = probe(self.profile.requested)
        self.say(f"realtime profile: granted {', '.join(sorted(self.profile.granted)) or 'nothing'}")
        warning = self.profile.warning()
        if warning:
            self.say(f"warning: {warning}")

    # ------------------------------------------------------------- helpers

    def _event(self, event, stage, episode, info):
        if self.cell is not None:
            self.cell.publish("runner/event", RUNNER_EVENT.encode(
                seq=0, stamp_ns=0, sent_ns=now_ns(), event=event, stage=stage, episode=episode, info=info))

    def _req(self, role, cmd, timeout=30.0, **args):
        return self.cell.request(role, cmd, timeout=timeout, **args)

    def _on_restart(self, role: str) -> None:
        """A service with a restart policy is back: it rejoins the episode in progress.
        The recorder writes on in a further part of the episode's recording (the gap is
        reported); the estimator's filter starts again where the reproduction is."""
        r = self.cell.restarts[-1]
        self.say(f"service {role} lost {r['lost_at_s']:.1f} s into the run (exit code {r['exit_code']}): "
                 f"restarted (restart: on_failure), back after {r['back_after_s']:.1f} s")
        if role == "foxglove_bridge":
            port = self.cell.request("foxglove_bridge", "status").get("port")
            self.say(f"live view: connect Foxglove to ws://127.0.0.1:{port} again")
        if self._episode is None:
            return
        kind, index, start = self._episode
        if role == "recorder":
            name = f"{kind}_{index:02d}.part{len(self._parts) + 2}.mcap"
            self._req("recorder", "begin_episode", path=name, kind=kind, index=index, scenario=self.scenario_text,
                      metadata=dict(self._episode_metadata, part=str(len(self._parts) + 2)))
            self._parts.append(self.recordings / name)
        elif role == "phase_estimator" and self._estimator_reset is not None:
            self._req("phase_estimator", "reset", resync=True, **self._estimator_reset)

    def _prepare(self, kind, index, start, model: str | None = None) -> Path:
        """Open the episode's recording and put the arm at its start; returns the
        recording's path as this runner sees it.  ``model``: the model file a reproduction
        runs (in the recording's metadata: what its visual topics draw the stiffness of)."""
        name = f"{kind}_{index:02d}.mcap"
        self._episode, self._parts = (kind, index, tuple(start)), []
        self._episode_metadata = {"start": json.dumps(list(start)), "scenario": self.scenario.name}
        if model is not None:
            self._episode_metadata["model"] = model
        # the recorder is told the name relative to its --out-dir, the one folder both
        # agree on: OUT/recordings (spawned), or a shared volume (--attach)
        written = self._req("recorder", "begin_episode", path=name, kind=kind, index=index,
                            scenario=self.scenario_text, metadata=self._episode_metadata)["path"]
        self._event("episode_begin", kind, index, {"start": list(start), **({"model": model} if model else {})})
        self._req("robot", "reset", start=list(start), episode=index, kind=kind)
        self._req("ft_sensor", "tare", samples=100)
        # realtime: the robot subscribes to what it applies only, so it does not wait for the sensor
        self._req("robot", "settle", cycles=200, wait_for=["ft"] if self.scenario.clock == "lockstep" else [],
                  timeout=120.0)
        path = self.recordings / name
        if self.options.attach and not path.exists():
            raise RecordingError(f"the recorder writes {written}, which this runner does not see at {path}: "
                                 f"with --attach the recorder's --out-dir must be this run's --out/recordings "
                                 f"(the same folder, e.g. a shared volume)")
        return path

    def _run_episode(self, answers_from, stop_on, max_seconds, label="episode") -> dict:
        """One episode of cycles (the robot's 'run'); returns the robot's summary.  In
        lockstep each cycle waits for ``answers_from``; in realtime a cycle closes as
        soon as they have answered, or at its deadline.  On a terminal a bar shows its
        simulated time and real-time factor."""
        bar = EpisodeProgress(label, max_seconds)
        try:
            summary = self.cell.run_episode(answers_from, stop_on, max_seconds,
                                            progress=bar.update if bar.enabled else None)
            if summary["reason"].startswith("unanswered:"):
                # lockstep: alive but silent (stopped, hung, cut off); the robot gave up on it.
                # The one that went silent may be further up the chain (the commander waits
                # for the estimator): whoever does not answer a status request is the one
                silent = [PARTICIPANTS.get(p, p) for p in summary["reason"].split(":", 1)[1].split(",")]
                stuck = self.cell.unresponsive(self.roles()) if hasattr(self.cell, "unresponsive") else []
                who = stuck or silent
                self._lost = launch.ServiceLost(
                    who[0], f"service {', '.join(who)} stopped answering"
                            f"{' (alive, no reply to a status request in 1 s)' if stuck else ''}: the robot's cycle "
                            f"{summary['last_seq']} ({summary['sim_seconds']:.3f} s simulated) and the one before went "
                            f"unanswered by {', '.join(silent)} for {LOCKSTEP_GIVE_UP} x the answer timeout, and "
                            f"the robot ended the episode", summary)
            return summary
        except launch.ServiceLost as exc:
            if exc.summary is None:
                raise
            # the robot stopped the episode when the service went: keep what it measured,
            # as a failed episode, then end the run (_stop_if_lost) with the error
            self._lost = exc
            return dict(exc.summary, reason=f"lost:{exc.role}")
        finally:
            bar.close()

    def _finish(self, kind, index, summary, topic_list):
        """The recorder closes the episode's file; with a service lost, whatever it can
        (None if the recorder is the one lost: the robot's summary is kept anyway)."""
        if self._lost is not None:
            topic_list = []  # what a lost service would have sent is not coming: do not wait for it
        try:
            rec = self._req("recorder", "end_episode", last_seq=summary["last_seq"], topics=topic_list,
                            timeout=30.0)
        except (launch.ServiceLost, TimeoutError, RuntimeError):
            if self._lost is None:
                raise
            rec = None
        if self._lost is None:
            self._event("episode_end", kind, index, {"reason": summary["reason"]})
        if self._parts:
            # the recorder was restarted during the episode: its first file ends where the
            # killed one stopped writing; say which cycles no part holds
            first = self.recordings / f"{kind}_{index:02d}.mcap"
            rec = dict(rec or {}, parts=[str(p) for p in self._parts],
                       gaps=recording_gaps([first, *self._parts]))
        self._episode, self._parts, self._estimator_reset = None, [], None
        return rec

    def _stop_if_lost(self) -> None:
        if self._lost is not None:
            raise self._lost

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
            summary = self._run_episode(["teacher"], "teacher_done", stage.max_seconds,
                                        label=f"demonstration {i + 1}/{len(starts)}")
            if self._lost is None:
                self._req("teacher", "idle")
            rec = self._finish("demonstration", index, summary, DEMO_TOPICS)
            self.state.demonstrations.append(dict(path=str(path), side=side, start=list(start), summary=summary,
                                                  recording=rec))
            self.say(f"demonstration {i + 1}/{len(starts)} ({side}): {summary['reason']} after "
                     f"{summary['sim_seconds']:.1f} s simulated / {summary['wall_seconds']:.1f} s wall, "
                     f"{'recording unfinished' if rec is None else str(rec['messages']) + ' messages recorded'}")
            self._stop_if_lost()

    def stage_learn(self, stage):
        sc = self.scenario
        t = time.monotonic()
        # choosing the number of phases is many independent fits: worth a pool of processes,
        # which then reads the demonstrations too (a fixed number of phases is one fit)
        with process_map(self.options.workers if stage.phases == "auto" else 1) as work_map:
            demos = list(work_map(functools.partial(load_demonstration, state=sc.state, features=sc.features),
                                  [d["path"] for d in self.state.demonstrations]))
            self.state.learned_from = [dict(path=d["path"], samples=len(s["states"])) for d, s in
                                       zip(self.state.demonstrations, demos)]
            n_phases = self._learn(stage, demos, work_map)
        self.state.learn_seconds = time.monotonic() - t
        self.say(f"learned {n_phases} phases in {self.state.learn_seconds:.1f} s; model {self.state.model_path}")

    def _learn(self, stage, demos, work_map) -> int:
        """Fit the model(s), save them and adopt the first learned task; the number of phases."""
        sc = self.scenario
        pairs = [(d["states"], d["forces"]) for d in demos]
        options = dict(n_restarts=stage.restarts)
        first, *others = stage.transitions
        with learning_threads(self.options.learn_threads):
            if stage.phases == "auto":
                self.say(f"learning: {stage.criterion.upper()} over {list(stage.candidates)} phases from "
                         f"{len(pairs)} demonstrations ({sum(len(s) for s, _ in pairs)} samples)")
                model, self.state.selection = fit_order(pairs, stage.candidates, stage.criterion, stage.selection,
                                                        transitions=first, seed=stage.seed,
                                                        max_iter=stage.max_iter, progress=self.say,
                                                        fit_map=work_map, **options)
            else:
                model = ETAR(int(stage.phases), first, **options).fit(
                    pairs, max_iter=stage.max_iter, seed=stage.seed)
                self.state.selection = dict(criterion="fixed", best=int(stage.phases), scores={}, log_likelihoods={
                    str(stage.phases): model.fit_report_.log_likelihood}, n_parameters={})
            models = [model]
            for transitions in others:
                # the comparison is between transition models, so the number of phases is the first's
                self.say(f"learning: {MODEL_NAMES[transitions]} with {model.n_phases} phases on the same "
                         f"demonstrations")
                models.append(ETAR(model.n_phases, transitions, **options).fit(
                    pairs, max_iter=stage.max_iter, seed=stage.seed))
            for i, m in enumerate(models):
                # which learned phase is which true phase is judged on the demonstrations only
                task = learn_task(m, demos, float(demos[0]["dt"]), state=sc.state, features=sc.features,
                                  selection=self.state.selection, sources=[d["path"] for d in demos])
                name = MODEL_NAMES[m.transitions]
                # a later scenario can reproduce with this file alone
                path = task.save(self.out / ("model.json" if i == 0 else f"model-{name}.json"))
                self.state.models[m.transitions] = dict(name=name, path=str(path), goal=task.goal.tolist(),
                                                        phase_to_truth=task.phase_to_truth)
                if i == 0:
                    self._adopt(task, path)
            if others:
                self._score_offline(models, demos)
        return model.n_phases

    def _score_offline(self, models, demos) -> None:
        """Each model's Viterbi and online filter against the demonstrations' true phases."""
        from etar.comparison import evaluate

        pairs = [(d["states"], d["forces"]) for d in demos]
        truths = [d["phases"] for d in demos]
        for m in models:
            e = evaluate(m, pairs, truths, float(demos[0]["dt"]), seed=self.scenario.learn_stage.seed)
            self.state.offline.append(dict(model=MODEL_NAMES[m.transitions], **e.to_dict()))
            self.say(f"offline, {MODEL_NAMES[m.transitions]}: filter accuracy {e.filtered.accuracy:.4f}, Viterbi "
                     f"{e.viterbi.accuracy:.4f}, {e.filtered.spurious_switches} spurious switches, "
                     f"one-step error near transitions {e.error_near_transitions:.3g}")

    def _adopt(self, task: LearnedTask, path: Path) -> None:
        self.state.model_path = str(path)
        self.state.goal = task.goal.tolist()
        self.state.phase_to_truth = task.phase_to_truth
        self.state.selection = task.selection

    def _use_model(self, path: Path) -> None:
        """A scenario's stored model (checked before anything starts)."""
        task = load_task(path)
        if task.state != self.scenario.state or task.features != self.scenario.features:
            raise TaskError(str(path), "metadata.state/features",
                            f"the model sees {task.state}/{task.features}, the scenario "
                            f"{self.scenario.state}/{self.scenario.features}", has_value=False)
        self._adopt(task, Path(path))
        self.say(f"model {path}: {task.n_phases} phases, goal {np.round(task.goal, 3).tolist()}")

    def _reproduction_models(self, stage) -> list[dict]:
        """The model(s) each start of ``stage`` is reproduced with."""
        if stage.transitions is None:
            return [dict(name=None, path=self.state.model_path, goal=self.state.goal,
                         phase_to_truth=self.state.phase_to_truth)]
        return [self.state.models[t] for t in stage.transitions]

    def stage_reproduce(self, stage):
        sc = self.scenario
        if self.state.model_path is None:
            raise RuntimeError("reproduce needs a learned model")
        demo_starts = [(d["side"], tuple(d["start"])) for d in self.state.demonstrations]
        starts = reproduction_starts(stage, sc.world, stage.seed, demo_starts)
        models = self._reproduction_models(stage)
        episodes = [(side, start, m) for side, start in starts for m in models]
        for i, (side, start, m) in enumerate(episodes):
            index = len(self.state.reproductions)
            model_path = str(Path(m["path"]).resolve())
            path = self._prepare("reproduction", index, start, model=model_path)
            self._estimator_reset = dict(model=model_path, episode=index)
            self._req("phase_estimator", "reset", **self._estimator_reset)
            goal = list(m["goal"])
            self._req("impedance_commander", "reset", model=model_path, episode=index, goal=goal,
                      goal_tolerance=stage.goal_tolerance)
            # counted within the stage (a scenario may have several); the recording is named by index
            label = f"reproduction {i + 1}/{len(episodes)}" + (f" ({m['name']})" if m["name"] else "")
            summary = self._run_episode(["command"], "goal_reached" if stage.stop_at_goal else None,
                                        stage.max_seconds, label=label)
            rec = self._finish("reproduction", index, summary, REPRO_TOPICS)
            self.state.reproductions.append(dict(path=str(path), side=side, start=list(start), summary=summary,
                                                 recording=rec, max_contact_force=stage.max_contact_force,
                                                 model=m["name"], phase_to_truth=m["phase_to_truth"]))
            self.say(f"{label} ({side}): {summary['reason']}, peak contact "
                     f"{summary['peak_contact_force']:.1f} N, {summary['sim_seconds']:.1f} s simulated / "
                     f"{summary['wall_seconds']:.1f} s wall")
            self._stop_if_lost()


def _check_port_free(port: int, host: str = "127.0.0.1") -> None:
    """Refuse a live-view port that is taken before anything starts (the bridge would
    only find out once the services are up)."""
    import socket

    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ValueError(f"--foxglove {port}: {host}:{port} is taken ({exc.strerror}); choose another port, "
                             "or 0 for any free one") from None


def run(options: RunOptions, progress=print) -> dict:
    return Runner(options, progress).run()
