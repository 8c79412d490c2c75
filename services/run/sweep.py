"""Parameter sweeps: every combination of some scenario parameters, times seeds, as
independent in-process runs in parallel; a table and plots of what came out.

    etar-bench sweep scenarios/valley.yaml --param cell.sensor_noise=0.5,1,2,4 --repeats 2 --out sweeps/noise

A parameter is a dotted path into the scenario, as ``Scenario.replace`` takes it: a
top-level key (``seed``, ``state``), a key of ``cell`` (``cell.sensor_noise``,
``cell.plate_friction``, ``cell.fri_packet_loss``), or a stage's key by the stage's kind
(``reproduce.start_perturbation``, ``demonstrate.count``; every stage of that kind, or
``reproduce[1].count`` for the second).  Values are YAML (``1e-3``, ``true``,
``[left, right]``), and every combination is a scenario value, validated before anything
runs (each is also written to ``scenarios/runNNN.yaml``, as a record of what ran).
``--repeats N`` runs each combination with the scenario's seed plus 0..N-1.

Runs go to a local process pool sized to the CPUs (``--workers``), or, with
``--cluster ADDRESS``, to a Dask distributed scheduler (``dask scheduler`` and
``dask worker ADDRESS`` on any machines that have this project installed and see
``--out``).  Each run's learner is held to ``--learn-threads`` (default: the CPUs
divided among the workers), since many learners on shared CPUs slow each other
down far more than they gain.

Output: ``table.csv`` and ``table.json`` (one row per run: the parameters, the
seed, phases chosen, reproductions that reached the goal, online phase accuracy,
transition-time error, peak contact force, times), one PNG per metric against
each parameter, and each run's directory under ``runs/`` as ``--record`` says:
``full`` everything, ``summary`` the report and the model, ``none`` nothing (only
``full`` draws Foxglove's visual topics into the recordings).

Ctrl-C or SIGTERM stops a local sweep: nothing starts after it, each run under way is
interrupted and writes its partial report, the workers are waited for (and killed after
20 s), and the table holds the runs that had finished, with ``sweep.json`` marked
``incomplete`` and naming the runs interrupted and those never started.  On a Dask
cluster it cancels there the runs not finished (``cancelled_on_cluster`` in
``sweep.json``); one already under way runs on to its end, as Dask does not stop a
running task.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import os
import shutil
import signal
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import yaml

from services.results.folder import SWEEP_FILE, SWEEP_PRODUCTS, holds_a_run
from services.scenario import Scenario, ScenarioError
from services.scenario.loading import StrictLoader
from services.runtime.files import write_file
from services.run.sweep_table import by_model_rows, plot, write_table

RECORD = ("full", "summary", "none")


class SweepError(ValueError):
    """A sweep that cannot be run, saying which parameter or value is at fault."""


# a sweep's runs (each seconds of CPU; 10000 are days) and local processes per CPU (each run is
# CPU-bound and holds a cell in memory): past these, a typo's digits fill the memory, not a table
MAX_RUNS, WORKERS_PER_CPU = 10_000, 4


@dataclass(frozen=True)
class Parameter:
    path: str
    values: tuple

    @classmethod
    def parse(cls, text: str) -> "Parameter":
        path, sep, values = text.partition("=")
        if not sep or not path.strip() or not values.strip():
            raise SweepError(f"--param {text!r}: expected PATH=V1,V2,... (e.g. cell.sensor_noise=0.5,1,2)")
        parsed = []
        for v in _split(values):
            try:
                parsed.append(yaml.load(v, Loader=StrictLoader))
            except yaml.YAMLError as exc:
                # one line: what YAML found, not its multi-line excerpt of the text
                problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
                raise SweepError(f"--param {path.strip()}: value {v!r} is not YAML ({problem})") from None
        if not parsed:
            raise SweepError(f"--param {text!r}: no values (expected PATH=V1,V2,..., e.g. cell.sensor_noise=0.5,1,2)")
        if len(set(map(repr, parsed))) != len(parsed):
            raise SweepError(f"--param {path}: the values repeat: {parsed}")
        return cls(path.strip(), tuple(parsed))


def _split(values: str) -> list[str]:
    """Split on commas outside brackets: ``[left],[left,right]`` is two values."""
    out, depth, cur = [], 0, ""
    for ch in values:
        if ch == "," and depth == 0:
            out.append(cur.strip())
            cur = ""
            continue
        depth += ch in "[{"
        depth -= ch in "]}"
        cur += ch
    out.append(cur.strip())
    return [v for v in out if v]


@dataclass(frozen=True)
class RunSpec:
    """One run of a sweep: where, what, and how."""

    index: int
    name: str
    params: dict
    scenario: Scenario
    out: str
    record: str
    learn_threads: int
    engine: str | None = None  # how the run's FRI cycles are stepped (None: the default)
    again: bool = False  # started again after its worker died: what the dead attempt left in its folder goes

    @property
    def seed(self) -> int:
        return self.scenario.seed

    def row(self, **figures) -> dict:
        """Its row of the sweep's table: the run, its parameters and seed, then ``figures``."""
        return dict(run=self.name, **{f"param {k}": v for k, v in self.params.items()}, seed=self.seed, **figures)

    def options(self):
        """The run's options: in one process, no figures, one learner process.  Foxglove's
        visual topics only where the recordings are kept (``full``): drawing them is about
        a twentieth of a run's CPU, and a sweep's runs share the CPUs."""
        from services.run.options import RunOptions

        return RunOptions(out=self.out, transport="inproc", engine=self.engine, figures=False,
                          run_id=f"sweep-{self.name}", learn_threads=self.learn_threads, workers=1,
                          recorder_args=() if self.record == "full" else ("--visual-rate-hz", "0"), replace=self.again)


def plan(base: Scenario, parameters: list, repeats: int, out: Path, record: str,
         learn_threads: int, engine: str | None = None, write: bool = True) -> list[RunSpec]:
    """Every combination x seed, as a scenario value (validated), each also written out
    under ``out/scenarios/`` as a record of what ran (``write_scenarios``); ``write=False``
    writes nothing, for a sweep that checks every value before it makes its folder."""
    if repeats < 1:
        raise SweepError(f"--repeats must be >= 1, got {repeats}")
    if record not in RECORD:
        raise SweepError(f"--record must be one of {', '.join(RECORD)}, got {record!r}")
    paths = [p.path for p in parameters]
    if len(set(paths)) != len(paths):
        raise SweepError(f"a parameter is given twice: {paths}")
    runs = math.prod(len(p.values) for p in parameters) * repeats
    if runs > MAX_RUNS:
        raise SweepError(f"--param values x --repeats {repeats} make {runs} runs, more than a sweep's {MAX_RUNS} "
                         "(split it into sweeps of their own)")
    specs = []
    combos = list(itertools.product(*[p.values for p in parameters])) if parameters else [()]
    for combo in combos:
        params = dict(zip(paths, combo))
        varied = base
        try:
            for path, value in params.items():
                varied = varied.replace(path, value)
        except ScenarioError as exc:
            raise SweepError(f"--param {exc}") from None
        for r in range(repeats):
            seed = varied.seed + r
            scenario = varied.replace("seed", seed)
            index = len(specs)
            name = f"run{index:03d}"
            specs.append(RunSpec(index, name, params, scenario, str(out / "runs" / name), record, learn_threads,
                                 engine))
    if write:
        write_scenarios(specs, out)
    return specs


def write_scenarios(specs: list[RunSpec], out: Path) -> None:
    """Each run's scenario under ``out/scenarios/``, once every combination is valid: a
    refused sweep leaves no sweep behind."""
    (out / "scenarios").mkdir(parents=True, exist_ok=True)
    for spec in specs:
        write_file(out / "scenarios" / f"{spec.name}.yaml", spec.scenario.to_yaml())




def _prepare(out_dir: Path, flag_value, replace: bool) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise SweepError(f"--out {flag_value}: {out_dir} is a file; --out names the sweep's folder")
    if out_dir.is_dir() and holds_a_run(out_dir):  # --replace removes a sweep, never a run
        raise SweepError(f"--out {flag_value}: {out_dir} holds a run (its report, recordings or model), not a "
                         "sweep; choose another folder")
    held = [name for name in SWEEP_PRODUCTS if (out_dir / name).exists()]
    if held and not replace:
        raise SweepError(f"--out {flag_value}: {out_dir} already holds a sweep ({', '.join(held)}); choose another "
                         "folder, or --replace to remove that sweep first")
    for name in held:
        path = out_dir / name
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    for png in out_dir.glob("*.png") if held else ():
        png.unlink()  # the earlier sweep's plots
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SweepError(f"--out {flag_value}: cannot make the sweep's folder ({exc.strerror or exc})") from None


def run_one(spec: RunSpec) -> dict:
    """One run in this process (a pool worker or a Dask worker): its table row."""
    from services.run.runner import Runner

    t0 = time.monotonic()
    lines = []
    row = spec.row()
    if _STOPPING:  # the sweep was interrupted: nothing starts after the signal
        return dict(row, error=f"not started: the sweep was interrupted ({_STOPPING})", interrupted="not started",
                    signal=_STOPPING, wall_s=0.0)
    global _RUNNING
    _RUNNING = True  # from here a signal interrupts the run (before, it only stops the worker)
    try:
        runner = Runner(spec.scenario, spec.options(), progress=lines.append)
        report = runner.run()
    except KeyboardInterrupt as exc:  # its partial report is in its folder (the runner wrote it)
        signal_name = str(exc) or "SIGINT"
        written = Path(spec.out) / "report.json"
        report = json.loads(written.read_text()) if written.exists() else None
        if report is None and not any((Path(spec.out) / "recordings").glob("*")):
            # interrupted while it was being set up, before any stage: it never started (its folder goes)
            shutil.rmtree(spec.out, ignore_errors=True)
            return dict(row, error=f"not started: the sweep was interrupted ({signal_name})",
                        interrupted="not started", signal=signal_name, wall_s=0.0)
        if report is None or report.get("error") is not None:
            return dict(row, error=f"interrupted ({signal_name})", interrupted="interrupted", signal=signal_name,
                        wall_s=time.monotonic() - t0)
        # the signal came once its stages had ended: the run is whole (its report says so)
    except Exception as exc:  # a run that cannot even start is a row with its error, not a dead sweep
        report = None
        row.update(error=f"{type(exc).__name__}: {exc}")
    finally:
        _RUNNING = False
    if report is not None:
        s = report["summary"]
        repro = report["reproductions"]
        row.update(
            error=report["error"], phases_chosen=s["phases_chosen"], reproductions=s["reproductions"],
            successes=s["successes"], success_rate=s["successes"] / s["reproductions"] if s["reproductions"] else None,
            online_phase_accuracy=s["online_phase_accuracy"], mean_transition_error_s=s["mean_transition_error_s"],
            peak_contact_force_n=max((r["peak_contact_force"] for r in repro), default=None),
            simulated_s=s["simulated_seconds"], episode_wall_s=s["episode_wall_seconds"],
            real_time_factor=s["real_time_factor"], learn_s=report["learning"].get("seconds"))
        if s.get("by_model"):
            # a run that reproduced with several models (ETAR and STAR): its figures per model
            from services.results.compare import run_summary

            row["by_model"] = {name: {k: v["mean"] for k, v in figures.items()}
                               for name, figures in run_summary([report]).items()}
    row["wall_s"] = time.monotonic() - t0
    out = Path(spec.out)
    if spec.record == "none":
        shutil.rmtree(out, ignore_errors=True)
    elif spec.record == "summary":
        shutil.rmtree(out / "recordings", ignore_errors=True)
    return row


# set in a pool worker by the first SIGINT or SIGTERM: the signal's name
_STOPPING = ""
_RUNNING = False  # a pool worker is in a run


def _on_stop_signal(signum, frame):
    """A pool worker's SIGINT and SIGTERM: the run under way is interrupted (it writes its
    partial report), and no later one starts; a second signal is not let in to cut that
    report short."""
    global _STOPPING
    if _STOPPING:
        return
    _STOPPING = signal.Signals(signum).name
    if _RUNNING:  # between runs the worker is waiting for the next: it will not start it
        raise KeyboardInterrupt(_STOPPING)


def _worker_init() -> None:
    signal.signal(signal.SIGINT, _on_stop_signal)
    signal.signal(signal.SIGTERM, _on_stop_signal)


def _pool(workers: int):
    import multiprocessing

    # spawn: a fresh interpreter per worker (numba's threads and Zenoh do not survive fork)
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_worker_init)


class SweepInterrupted(KeyboardInterrupt):
    """A sweep stopped by SIGINT or SIGTERM: the rows of the runs it had (``execute``), and
    once they are tabulated, the sweep's summary (``sweep``)."""

    def __init__(self, why: str, rows: list | None = None, summary: dict | None = None,
                 cancelled: list | None = None):
        super().__init__(why)
        self.why, self.rows, self.summary = why, rows or [], summary
        self.cancelled = cancelled  # a cluster's sweep: the runs it had not finished, cancelled there


# how long the pool's workers get to write their interrupted runs' reports before they are killed
_STOP_GRACE_S = 20.0


def _stop_pool(pool, futures) -> None:
    """Cancel the runs not started, tell each worker to stop (it writes the partial report of
    the run it has), wait for them, and kill any that outlives the grace: none outlives the
    sweep."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)  # idle workers get their end; queued runs are dropped
    for p in processes:
        try:
            os.kill(p.pid, signal.SIGTERM)
        except (ProcessLookupError, TypeError):
            pass
    deadline = time.monotonic() + _STOP_GRACE_S
    for p in processes:
        p.join(max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
            p.join(5.0)


def execute(specs: list[RunSpec], workers: int, cluster: str | None, say=print) -> list[dict]:
    """Run every spec, locally or on a Dask cluster; rows in spec order."""
    rows: dict[int, dict] = {}
    bar = _progress(len(specs))
    t0 = time.monotonic()

    def done(spec, row):
        rows[spec.index] = row
        rtf = row.get("real_time_factor")
        bar.update(1)
        bar.set_postfix_str(f"{spec.name} {spec.params or ''} seed {spec.seed}: "
                            f"{'failed' if row.get('error') else 'ok'}"
                            f"{'' if rtf is None else f', {rtf:.1f}x real time'}")
        say(f"{spec.name} ({', '.join(f'{k}={v}' for k, v in spec.params.items()) or 'as is'}, seed {spec.seed}): "
            + (f"FAILED {row['error']}" if row.get("error") else
               f"{row.get('phases_chosen')} phases, {row.get('successes')}/{row.get('reproductions')} reached the "
               f"goal, accuracy {_fmt(row.get('online_phase_accuracy'))}, {row['wall_s']:.0f} s")
            + f"  [{len(rows)}/{len(specs)}, {time.monotonic() - t0:.0f} s]")

    if cluster:
        from distributed import Client, as_completed as dask_completed  # installed: sweep() checked --cluster

        with Client(cluster, timeout="30s") as client:
            say(f"sweep: {len(specs)} runs on the Dask cluster at {cluster} "
                f"({len(client.scheduler_info()['workers'])} workers)")
            futures = {client.submit(run_one, spec, pure=False, key=f"etar-{spec.name}-{time.time_ns()}"): spec
                       for spec in specs}
            try:
                for fut in dask_completed(futures):
                    done(futures[fut], fut.result())
            except KeyboardInterrupt as exc:
                bar.close()
                left = [f for f in futures if not f.done()]
                client.cancel(left)
                say(f"sweep: interrupted ({str(exc) or 'SIGINT'}): the {len(left)} run(s) not finished are cancelled "
                    "on the cluster; one already under way there runs on to its end (Dask does not stop a running "
                    "task) and may still write into its folder")
                raise SweepInterrupted(str(exc) or "SIGINT", [rows[i] for i in sorted(rows)],
                                       cancelled=sorted(futures[f].name for f in left)) from None
    elif workers <= 1:
        say(f"sweep: {len(specs)} runs in this process")
        for spec in specs:
            row = run_one(spec)
            done(spec, row)
            if row.get("interrupted"):  # the Ctrl-C (or SIGTERM) was the sweep's: no run after it
                bar.close()
                raise SweepInterrupted(row["signal"], [rows[i] for i in sorted(rows)])
    else:
        say(f"sweep: {len(specs)} runs on {workers} local processes")
        pending, died = list(specs), None
        while pending:
            pool = _pool(min(workers, len(pending)))
            futures = {pool.submit(run_one, spec): spec for spec in pending}
            try:
                for fut in as_completed(futures):
                    try:
                        row = fut.result()
                    except BrokenProcessPool as exc:
                        # a worker was killed (the OOM killer, a kill -9): the pool's every run not finished
                        # fails with it, the other worker's too
                        died = died or f"{type(exc).__name__}: {exc}"
                        continue
                    done(futures[fut], row)
            except KeyboardInterrupt as exc:
                bar.close()
                say(f"sweep: interrupted ({str(exc) or 'SIGINT'}): stopping the workers; the runs under way write "
                    "their partial reports")
                _stop_pool(pool, futures)
                for fut, spec in futures.items():  # finished while the signal was handled
                    if spec.index not in rows and fut.done() and not fut.cancelled() and fut.exception() is None:
                        rows[spec.index] = fut.result()
                raise SweepInterrupted(str(exc) or "SIGINT", [rows[i] for i in sorted(rows)]) from None
            pool.shutdown(wait=True)
            unfinished = [spec for spec in pending if spec.index not in rows]
            if not unfinished:
                break
            if any(spec.again for spec in unfinished):  # its pool broke a second time: said, not tried again
                say(f"sweep: a worker process died again ({died}): the {len(unfinished)} run(s) it left unfinished "
                    "are failed rows")
                for spec in unfinished:
                    done(spec, spec.row(error=f"its worker process died twice ({died})", wall_s=0.0))
                break
            say(f"sweep: a worker process died ({died}); the {len(unfinished)} run(s) it left unfinished start "
                "again in a new pool")
            pending = [dataclasses.replace(spec, again=True) for spec in unfinished]
    bar.close()
    return [rows[i] for i in sorted(rows)]


def _progress(total: int):
    from tqdm import tqdm

    return tqdm(total=total, unit="run", file=sys.stderr, disable=not sys.stderr.isatty(), dynamic_ncols=True)


def _fmt(v, digits=3):
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _tabulate_interrupted(stop: SweepInterrupted, specs, out_dir: Path, scenario, parameters, repeats,
                          wall: float) -> dict:
    """The table of the runs that finished before the signal, and sweep.json marked
    incomplete (which runs were interrupted, which never started)."""
    rows = [r for r in stop.rows if not r.get("interrupted")]
    interrupted = [r["run"] for r in stop.rows if r.get("interrupted") == "interrupted"]
    finished = {r["run"] for r in rows}
    cancelled = stop.cancelled or []
    not_started = [s.name for s in specs if s.name not in finished and s.name not in interrupted
                   and s.name not in cancelled]
    csv_path, _ = write_table(by_model_rows(rows), out_dir) if rows else (None, None)
    summary = dict(scenario=scenario.source, parameters={p.path: list(p.values) for p in parameters},
                   repeats=repeats, runs=len(rows), failed=sum(1 for r in rows if r.get("error")),
                   wall_seconds=wall, incomplete=f"interrupted ({stop.why})", interrupted_runs=interrupted,
                   not_started=not_started, table=None if csv_path is None else str(csv_path))
    if stop.cancelled is not None:
        summary["cancelled_on_cluster"] = cancelled
    write_file(out_dir / SWEEP_FILE, json.dumps(summary, indent=1) + "\n")
    return summary


def sweep(scenario: Scenario, parameters: list, *, repeats: int, out: str, record: str = "summary",
          workers: int | None = None, cluster: str | None = None, learn_threads: int | None = None,
          replace: bool = False, say=print, engine: str | None = None) -> dict:
    from etar.parsing import empty_path
    from services.run.options import check_cluster
    from services.runtime.threads import available_cpus
    from services.transport.carriers import check_engine

    try:
        empty_path("--out", out, "the sweep's folder")
    except ValueError as exc:
        raise SweepError(str(exc)) from None
    out_dir = Path(out).expanduser().resolve()
    cpus = available_cpus()
    for flag, value, most, why in (("--workers", workers, WORKERS_PER_CPU * cpus, f" ({WORKERS_PER_CPU} x the {cpus} "
                                                                                  "CPUs this process may use)"),
                                   ("--learn-threads", learn_threads, None, ""), ("--repeats", repeats, MAX_RUNS, "")):
        if value is not None and not 1 <= value <= (most or value):
            raise SweepError(f"{flag} must be {'>= 1' if value < 1 else f'<= {most}{why}'}, got {value}")
    try:
        check_engine(engine, in_process=True)
        if cluster is not None:
            check_cluster(cluster)
    except ValueError as exc:
        raise SweepError(str(exc)) from None
    workers = cpus if workers is None else workers
    threads = learn_threads or max(1, cpus // workers)
    specs = plan(scenario, parameters, repeats, out_dir, record, threads, engine, write=False)
    _prepare(out_dir, out, replace)  # every value checked: only now is anything made or removed
    write_scenarios(specs, out_dir)
    t0 = time.monotonic()
    try:
        rows = execute(specs, min(workers, len(specs)), cluster, say)
    except SweepInterrupted as stop:
        raise SweepInterrupted(stop.why, stop.rows, _tabulate_interrupted(stop, specs, out_dir, scenario, parameters,
                                                                          repeats, time.monotonic() - t0),
                               stop.cancelled) from None
    wall = time.monotonic() - t0
    n_runs, n_failed = len(rows), sum(1 for r in rows if r.get("error"))
    rows = by_model_rows(rows)
    from services.results.compare import comparison_over_seeds

    comparison = comparison_over_seeds(rows)
    if comparison:
        write_file(out_dir / "comparison.txt", "\n".join(comparison) + "\n")
        say("\n".join(comparison))
        parameters = [*parameters, Parameter("model", tuple(dict.fromkeys(r["param model"] for r in rows
                                                                             if r.get("param model"))))]
    csv_path, json_path = write_table(rows, out_dir)
    pngs = plot(rows, parameters, out_dir)
    summary = dict(scenario=scenario.source, parameters={p.path: list(p.values) for p in parameters}, repeats=repeats,
                   runs=n_runs, failed=n_failed, wall_seconds=wall,
                   workers=workers, cluster=cluster, learn_threads=threads, engine=engine,
                   table=str(csv_path), plots=[str(p) for p in pngs],
                   comparison=str(out_dir / "comparison.txt") if comparison else None)
    write_file(out_dir / SWEEP_FILE, json.dumps(summary, indent=1) + "\n")
    return summary
