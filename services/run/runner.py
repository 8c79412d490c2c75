"""The scenario runner: it walks a scenario's stages on a cell and leaves the run's folder.

    Runner(load_scenario("scenarios/valley.yaml"), RunOptions(out="runs/valley")).run()

Stages (``services.scenario``):

- demonstrate: per demonstration, the recorder opens a file, the robot is put at the
  start in gravity compensation, the sensor is tared while the arm rests, the teacher
  guides the arm until it is done (``services.run.episode``);
- learn: ETAR is fitted to the recorded MCAP files (BIC over the candidates, or a fixed
  number of phases), and every phase's impedance is derived (``services.run.learn``);
- reproduce: per reproduction, the robot starts where no demonstration did, in Cartesian
  impedance under FRI command mode; the estimator and the commander close the loop
  until the goal is reached (or time runs out; with ``stop_at_goal: false`` for the
  whole time, holding at the goal).

A scenario with a ``model`` file reproduces with that model (learned by an earlier run,
which stored the goal and the phase mapping in its metadata) instead of learning one.
What the run did goes into a ``RunRecord``; everything the report says is measured from
it, the recordings and the services' own statistics (``services.results.report``).
"""

from __future__ import annotations

import signal
import threading
import time
import uuid
from pathlib import Path

from etar.interrupts import interrupt_behind
from services.results.decoding import LearnerView
from services.results.folder import SCENARIO_FILE, check_run_folder, prepare_run_folder
from services.results.record import EpisodeRecord, RunRecord
from services.results.report import episode_readings, write_report
from services.ros2.wire import FULL_NODE_NAME
from services.run.configs import node_configs
from services.run.episode import Episodes, Recording
from services.run.learn import DemonstrationReads, learn, stored_model
from services.run.options import RunOptions
from services.run.preflight import preflight, start_problem
from services.run.realtime_profile import Grant, parse_profile, placement, probe
from services.run.report_reads import ReportReads
from services.run.serve import SERVED_TOPICS, served_start
from services.scenario import Scenario
from services.scenario.starts import teacher_seed
from services.runtime.files import write_file
from services.runtime.provenance import provenance
from services.transport.cell import Start


class Runner:
    def __init__(self, scenario: Scenario, options: RunOptions, progress=print):
        self.scenario = scenario
        self.options = options
        self.say = progress
        self.roles = options.roles(scenario)
        # every option, the hosts layout and every credential checked before anything starts
        self.transport = options.carrier(scenario)
        # and what the services would find only once they are up: the model file, the starts
        self.preflight = preflight(scenario)
        if options.serve is not None:
            _check_serving(scenario, options.serve)
        # resolved once, here: every path handed to a service or written in the report
        # follows from this absolute folder (a relative one, joined again by the
        # recorder, doubled itself: out/valley/recordings/out/valley/recordings/)
        self.out = Path(options.out).expanduser().resolve()
        self.recordings = self.out / "recordings"
        self.run_id = options.run_id or f"{scenario.name}-{uuid.uuid4().hex[:8]}"
        self.record = RunRecord(scenario_name=scenario.name, source=scenario.source, clock=scenario.clock,
                                run_id=self.run_id, out=self.out, transport=self.transport.name,
                                engine=getattr(self.transport, "engine", None),
                                wire="udp" if options.serve is not None else options.wire, world=scenario.world,
                                workers=options.workers, provenance=provenance(options.command),
                                # the scenario's view is its model's: the learn stage's, and a stored
                                # model's too (the preflight checked it)
                                figures=LearnerView(scenario.state, scenario.features, scenario.state_resolution)
                                if options.figures else None)
        self.cell = None
        self.episodes = None
        self.report_reads = ReportReads(scenario.clock == "lockstep" and options.workers != 1, say=self.say)
        self.ready = threading.Event()  # set once every service is up (tests and benches wait on it)
        self._interrupted = False  # a Ctrl-C or SIGTERM has been taken
        self._late_signal = ""  # one that came once the stages had ended (raised after the report)
        self._handlers_before: dict = {}  # SIGINT's and SIGTERM's handlers before escalate took them
        self.profile = Grant(parse_profile(options.realtime_profile) if scenario.clock == "realtime"
                             else frozenset())
        check_run_folder(self.out, options.out, replace=options.replace)
        # every service's config, its flags checked: a bad one is refused before anything starts
        self.configs = node_configs(scenario, options, self.roles, self.recordings,
                                    self.transport.offloads_recording)
        # the last check before anything starts: where the run goes (a folder, not holding a
        # run unless asked to replace it: nothing of another run may be mistaken for this one's)
        prepare_run_folder(self.out, options.out, replace=options.replace)
        try:
            self.recordings.mkdir(parents=True, exist_ok=True)
            # the scenario as run, every default filled in: what `etar-bench run` takes back
            write_file(self.out / SCENARIO_FILE, scenario.to_yaml())
        except OSError as exc:
            raise ValueError(f"--out {options.out}: cannot make the run's folder {self.recordings} "
                             f"({exc.strerror or exc})") from None

    # ----------------------------------------------------------------- run

    def run(self) -> dict:
        try:
            return self._run()
        finally:  # the handlers it replaced, back (a sweep's worker runs the next with its own); attached,
            if not self.options.attach:  # SIGTERM stays ignored: the container's end follows (_ignore_the_ending)
                for sig, handler in self._handlers_before.items():
                    signal.signal(sig, handler)

    def _run(self) -> dict:
        sc = self.scenario
        t0 = time.monotonic()
        self.say(f"run {self.run_id}: scenario {sc.name} ({sc.source}), clock {sc.clock}, transport "
                 f"{self.transport.name}, output {self.out}")
        error = None
        codes = {}
        try:
            if sc.model is not None and self.options.serve is None:
                self.record.learning = stored_model(sc, self.preflight.model, self.say)
            self.profile = _granted(self.profile, self.transport, self.say)
            self._start_cell()
            self.say(f"services ready ({', '.join(self.roles)}) after {time.monotonic() - t0:.1f} s")
            self.ready.set()
            if self.options.serve is not None:
                self.serve(self.options.serve)
            else:
                with DemonstrationReads(sc, self.options.workers, self.say) as self.reads, self.report_reads:
                    for index, stage in enumerate(sc.stages):
                        # the starts the preflight drew and found within reach, drawn once
                        getattr(self, f"stage_{stage.kind}")(stage, self.preflight.stage_starts(index))
            self.episodes.event("run_end", "", -1, {})
        except BaseException as caught:
            # a Ctrl-C inside compiled code (the learn stage's fits) comes as numba's SystemError
            exc = interrupt_behind(caught) or caught
            if isinstance(exc, KeyboardInterrupt):
                self._interrupted = True
            # before the first line that says the run failed: a Ctrl-C after it escalates
            self._escalate_on_next_interrupt()
            error = (f"interrupted ({str(exc) or 'SIGINT'})" if isinstance(exc, KeyboardInterrupt)
                     else f"{type(exc).__name__}: {exc}")
            self.say(f"run failed: {error}")
            if self.cell is not None:
                for line in self.cell.post_mortem():
                    self.say(line)
            if isinstance(exc, KeyboardInterrupt):
                if exc is caught:
                    raise
                raise exc from None
        finally:
            # from here a signal must not cut the report short (_escalate_on_next_interrupt).
            # Whatever fails here, the services, the session and the hosts are let go (the
            # outer finally) and the profile's hold on the machine too (the inner one)
            self._escalate_on_next_interrupt()
            try:
                try:
                    if self.cell is not None:
                        self.record.service_stats = self.cell.statistics(self.roles)
                        self.record.restarts = list(self.cell.restarts)
                        self.record.hosts = self.cell.where()
                        try:
                            codes = self.cell.stop(self.roles, before_report=True)
                        except Exception as exc:  # noqa: BLE001 - a service that cannot finish: said, and the report still written
                            stopping = f"stopping the services: {type(exc).__name__}: {exc}"
                            self.say(f"run failed: {stopping}" if error is None else stopping)
                            error = error or stopping
                        unclean = _unclean_exits(codes, getattr(self.cell, "lost", {}))
                        if unclean:
                            stopping = f"stopping the services: {unclean}"
                            self.say(f"run failed: {stopping}" if error is None else stopping)
                            error = error or stopping
                finally:
                    self.profile.release()
                if self.profile.requested:
                    self.record.realtime_profile = self.profile.to_dict()
                report = write_report(self.record, codes, error, time.monotonic() - t0, self.report_reads.decoded)
                if self.options.figures:
                    from services.results.html import write_figures_and_page

                    self.say(write_figures_and_page(self.out, run=self.record,
                                                    ahead=self.report_reads.ahead.get("figures")))
            finally:
                if self.cell is not None:
                    if self.options.attach:
                        self._ignore_the_ending()
                    self.cell.stop(self.roles, before_report=False)
        if self._late_signal:  # the stages had ended, the report is whole: the signal is still said
            raise KeyboardInterrupt(self._late_signal)
        return report

    def _start_cell(self) -> None:
        o = self.options
        restartable = {role for role, policy in self.scenario.restart if policy == "on_failure"}
        if o.foxglove is not None:
            restartable.add("foxglove_bridge")  # a view of the run: losing it must not cost the run
        if o.ros2 is not None:
            restartable.add("ros2")  # ROS 2's view of the run, likewise
        start = Start(clock=self.scenario.clock, log_dir=self.out / "logs", ready_timeout=o.ready_timeout,
                      restartable=frozenset(restartable), on_restart=self._on_restart,
                      placement=lambda role: placement(role, self.profile, sched_fifo=o.sched_fifo,
                                                       fifo_priorities=o.fifo_priorities,
                                                       isolate_robot=o.isolate_robot))
        self.cell = self.transport.open(self.run_id, self.configs, start)
        self.episodes = Episodes(self.cell, clock=self.scenario.clock, roles=self.roles, recording=Recording(
            self.recordings, self.scenario.to_yaml(), self.scenario.name, attached=o.attach))
        self.cell.start()
        hosts = self.cell.where()
        if hosts:
            self.say("hosts: " + "; ".join(f"host {h['name']} ({h['address']}): {', '.join(h['roles'])}"
                                           for h in hosts))
        if o.foxglove is not None:
            port = self.cell.request("foxglove_bridge", "status").get("port")
            self.say(f"live view: connect Foxglove to ws://127.0.0.1:{port} (docs/foxglove/README.md)")
        if o.ros2 is not None:
            through = getattr(self.cell, "endpoint", "") or ", ".join(o.zenoh.connect if o.zenoh else ())
            self.say(f"ROS 2: the cell is node {FULL_NODE_NAME} in domain {o.ros2}, on the Zenoh session at "
                     f"{through} (rmw_zenoh in client mode connects there; docs/ros2.md)")

    # -------------------------------------------------------------- stages

    def stage_demonstrate(self, stage, starts):
        for i, (side, start) in enumerate(starts):
            index = len(self.record.demonstrations)
            label = f"demonstration {i + 1}/{len(starts)}"
            summary, rec, path = self.episodes.demonstrate(index, start, seed=teacher_seed(stage.seed, i),
                                                           goal_x=stage.goal_x, max_seconds=stage.max_seconds,
                                                           label=label)
            self.record.demonstrations.append(EpisodeRecord(str(path), side, list(start), summary, rec))
            self.reads.read(str(path))  # for the learn stage, while the next demonstrations run
            self.say(f"{label} ({side}): {summary['reason']} after {summary['sim_seconds']:.1f} s simulated / "
                     f"{summary['wall_seconds']:.1f} s wall, "
                     f"{'recording unfinished' if rec is None else str(rec['messages']) + ' messages recorded'}")
            self.episodes.raise_if_lost()

    def stage_learn(self, stage, starts):  # a learn stage has no episodes: ``starts`` is empty
        learning = self.record.learning = learn(
            stage, self.scenario, [d.path for d in self.record.demonstrations], self.out, workers=self.options.workers,
            threads=self.options.learn_threads, say=self.say, reads=self.reads)
        if self.options.figures and learning.demonstrations:
            _draw_learning_figures_beside(self.report_reads, self.out, self.record)

    def stage_reproduce(self, stage, starts):
        learning = self.record.learning
        if learning.model is None:
            raise RuntimeError("reproduce needs a learned model")
        # the model(s) each start is reproduced with: the run's, or each listed transition model's
        models = ([learning.models[t] for t in stage.transitions] if stage.transitions is not None
                  else [None])
        episodes = [(side, start, m) for side, start in starts for m in models]
        for i, (side, start, m) in enumerate(episodes):
            index = len(self.record.reproductions)
            model = learning.model if m is None else m
            name = None if m is None else m.name  # named only when the stage lists its models
            # counted within the stage (a scenario may have several); the recording is named by index
            label = f"reproduction {i + 1}/{len(episodes)}" + (f" ({name})" if name else "")
            summary, rec, recording = self.episodes.reproduce(
                index, start, model=str(Path(model.path).resolve()), goal=model.goal,
                goal_tolerance=stage.goal_tolerance,
                stop_at_goal=stage.stop_at_goal, max_seconds=stage.max_seconds, label=label)
            self.record.reproductions.append(EpisodeRecord(
                str(recording), side, list(start), summary, rec, max_contact_force=stage.max_contact_force,
                model=name, phase_to_truth=model.phase_to_truth))
            self.report_reads.catch_up(episode_readings(self.record))  # decoded while the next ones run
            self.say(f"{label} ({side}): {summary['reason']}, peak contact "
                     f"{summary['peak_contact_force']:.1f} N, {summary['sim_seconds']:.1f} s simulated / "
                     f"{summary['wall_seconds']:.1f} s wall")
            self.episodes.raise_if_lost()

    def serve(self, serve) -> None:
        """etar-bench serve: one episode for a lab's FRI remote (services.run.serve)."""
        start = served_start(self.scenario, serve)
        path = self.episodes.begin("served", 0, start)
        status = self.cell.request("robot", "status")["fri_udp"]
        self.say(f"serving FRI 1.0 over UDP from {status['address'][0]}:{status['address'][1]} to the remote at "
                 f"{status['remote'][0]}:{status['remote'][1]} (KRL program {status['krl']}, cycle "
                 f"{serve.fri_cycle_ms} ms), the arm held at "
                 f"{', '.join(f'{v:.3f}' for v in start)} m in monitor mode"
                 + (f"; Net F/T box on {self._netft_where()}" if serve.netft else "")
                 + f"; for {serve.max_seconds:g} s (Ctrl-C ends it sooner)")
        try:
            summary = self.episodes.run([], None, serve.max_seconds, label="served")
        except KeyboardInterrupt:
            # Ctrl-C (or SIGTERM) is how serving ends sooner: the episode ends there, with
            # its summary and the report; a second one aborts (_escalate_on_next_interrupt)
            self._interrupted = True
            self._escalate_on_next_interrupt()
            self.say("interrupted: ending the served episode (again to abort)")
            summary = self.cell.stop_episode()
            if summary is None:
                raise
        rec = self.episodes.finish("served", 0, summary, SERVED_TOPICS)
        self.record.served.append(EpisodeRecord(str(path), "-", list(start), summary, rec))
        wire = summary.get("wire") or {}
        d = wire.get("datagrams") or {}
        self.say(f"served: {summary['reason']} after {summary['sim_seconds']:.1f} s; {d.get('accepted', 0)} commands "
                 f"in time of {d.get('sent', 0)} measurements; command mode {wire.get('command_mode_s', 0.0):.1f} s; "
                 f"peak contact {summary['peak_contact_force']:.1f} N")
        self.episodes.raise_if_lost()

    def _netft_where(self) -> str:
        box = self.cell.request("ft_sensor", "status").get("netft") or {}
        return (f"{box.get('address')} (RDT UDP {box.get('rdt_port')}, HTTP {box.get('http_port')}, "
                f"calibration TCP {box.get('calibration_port')})")

    # ------------------------------------------------------------- around the stages

    def _on_restart(self, role: str) -> None:
        """A service with a restart policy is back: say so, and it rejoins the episode in progress."""
        r = self.cell.restarts[-1]
        self.say(f"service {role} lost {r['lost_at_s']:.1f} s into the run (exit code {r['exit_code']}): "
                 f"restarted (restart: on_failure), back after {r['back_after_s']:.1f} s")
        if role == "foxglove_bridge":
            port = self.cell.request("foxglove_bridge", "status").get("port")
            self.say(f"live view: connect Foxglove to ws://127.0.0.1:{port} again")
        self.episodes.rejoin(role)

    def _ignore_the_ending(self) -> None:
        """Attached, the report is written and stopping the services follows: their runtime
        answers it by ending a whole run (docker-compose's --exit-code-from stops every
        container left, this one with SIGTERM).  The run is whole, its exit status the
        command's: SIGTERM is ignored from here, and stays so (``run`` does not give the
        handlers back; SIG_IGN, unlike a Python handler, survives the interpreter's exit)."""
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, signal.SIG_IGN)

    def _escalate_on_next_interrupt(self) -> None:
        """The services are being stopped and the report written, after the stages or after
        an interrupt.  A Ctrl-C (or SIGTERM) must not abort that half-way (leaving orphans
        and no report): the first one after the stages ended lets the clean-up finish (and
        is raised once the report is written); one after an interrupt kills the services at
        once and lets the clean-up finish."""
        if threading.current_thread() is not threading.main_thread():
            return

        def escalate(signum, frame):
            name = signal.Signals(signum).name
            if not self._interrupted:
                self._interrupted, self._late_signal = True, name
                self.say(f"{name}: the run's stages have ended; the report is being written (again to kill the "
                         "services at once)")
                return
            killed = self.cell.kill() if self.cell is not None else 0
            self.say(f"{name} again: killing the {killed} service process{'' if killed == 1 else 'es'} "
                     "still running now")

        for sig in (signal.SIGINT, signal.SIGTERM):
            self._handlers_before.setdefault(sig, signal.getsignal(sig))
            signal.signal(sig, escalate)


def _granted(profile: Grant, transport, say) -> Grant:
    """What the realtime profile is granted, found out before any service starts; a refusal's
    cost said in one line."""
    if not profile.requested:
        return profile
    if not transport.spawns:
        profile.refused = {p: "the services were started by someone else (--attach)" for p in sorted(profile.requested)}
    else:
        profile = probe(profile.requested)
    say(f"realtime profile: granted {', '.join(sorted(profile.granted)) or 'nothing'}")
    warning = profile.warning()
    if warning:
        say(f"warning: {warning}")
    return profile


def _check_serving(scenario: Scenario, serve) -> None:
    """What serving a lab's remote needs of the scenario (ValueError)."""
    if scenario.clock != "realtime":
        raise ValueError("serving a lab's remote needs the realtime clock (etar-bench serve sets it)")
    start = served_start(scenario, serve)
    problem = start_problem(start)
    if problem:
        raise ValueError(f"--start {','.join(f'{v:g}' for v in start)}: {problem}")


def run(scenario: Scenario, options: RunOptions, progress=print) -> dict:
    return Runner(scenario, options, progress).run()


def _draw_learning_figures_beside(reads: ReportReads, out: Path, record: RunRecord) -> None:
    """The figures of the demonstrations and the learning need no reproduction: drawn beside
    the reproductions, the report's figures then add the reproduction's (write_figures_and_page)."""
    from services.results.figures import learning_figures

    learning = record.learning
    reads.start("figures", learning_figures, (str(out), learning.model_path, record.world,
                                              [d.path for d in record.demonstrations], learning.demonstrations,
                                              learning.selection), episode_readings(record))


def _unclean_exits(codes: dict, lost) -> str:
    """The services that did not end by themselves when asked to (a signal ended them, or an
    error code), a lost one aside (its loss is the run's error already): one phrase, or ''."""
    parts = []
    for role, code in sorted(codes.items()):
        if code in (0, None) or role in lost:
            continue
        if code < 0:
            try:
                name = signal.Signals(-code).name
            except ValueError:
                name = f"signal {-code}"
            parts.append(f"{role} did not exit when asked and was ended by {name} (exit code {code})")
        else:
            parts.append(f"{role} exited with code {code}")
    return "; ".join(parts)
