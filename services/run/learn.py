"""The learn stage: ETAR (and STAR, for the comparison) fitted to the recorded demonstrations,
the number of phases chosen by BIC/AIC or fixed, every phase's impedance derived, the
models saved; or a scenario's stored model, checked against the scenario."""

from __future__ import annotations

import contextlib
import functools
import hashlib
import time
from pathlib import Path

import numpy as np

from etar import ETAR
from etar.comparison import MODEL_NAMES, evaluate
from etar.selection import demonstration_fits, fit_candidate, fit_order
from etar.task import learn_task
from services.recordings.demonstrations import load_demonstration
from services.results.record import LearningRecord, ModelRecord
from services.runtime.files import write_via
from services.runtime.threads import FallbackMap, learning_threads, process_map
from services.scenario import LearnStage, Scenario


POOL = "the learn stage's pool of processes"


def _reader(scenario: Scenario):
    return functools.partial(load_demonstration, state=scenario.state, features=scenario.features,
                             state_resolution=scenario.state_resolution)


def _job_key(job: tuple) -> tuple:
    """A candidate fit's job (``etar.selection.vote_jobs``) as a value to find it by: its
    demonstrations by their bytes, the rest as it is."""
    demos, k, transitions, options, max_iter, tol, seed = job
    digest = hashlib.sha1()
    for arrays in demos:
        for a in arrays:
            digest.update(f"{a.dtype}{a.shape}".encode())
            digest.update(np.ascontiguousarray(a).tobytes())
    return digest.hexdigest(), k, transitions, tuple(sorted(options.items())), max_iter, tol, seed


def _read_and_vote(job: tuple) -> tuple[dict, list]:
    """A demonstration read, and the candidate fits the per-demonstration vote runs for it:
    (the demonstration, [(job key, fitted model)])."""
    load, path, vote = job
    demo = load(path)
    fits = demonstration_fits((demo["states"], demo["forces"]), **vote)
    return demo, [(_job_key(j), fit_candidate(j)) for j in fits]


class DemonstrationReads:
    """The learn stage's pool of processes, started with the first demonstration of a run
    whose learn stage chooses the number of phases, reading each recording as soon as it is
    written: the 2.5 s that starting the pool and reading took at the start of the valley's
    learn stage pass during its demonstrations (in one process the episodes take one core
    of two).  When the stage votes per demonstration, the vote's fits of each demonstration
    run then too (``fit_map`` hands them to the vote, which runs the others).  Lockstep
    only: on the realtime clock that work would take CPU the 1 kHz loop needs.  The learn
    stage takes the pool over and closes it; as a context manager it is closed with the
    run, its workers terminated when the run failed."""

    def __init__(self, scenario: Scenario, workers: int | None, say=print):
        stage = next((s for s in scenario.stages if s.kind == "learn"), None)
        self.wanted = stage is not None and stage.phases == "auto" and scenario.clock == "lockstep"
        self._workers, self._load, self._say = workers, _reader(scenario), say
        # what fit_order's vote runs for each demonstration (services.run.learn._fit)
        self._vote = dict(candidates=stage.candidates, criterion=stage.criterion, transitions=stage.transitions[0],
                          seed=stage.seed, max_iter=stage.max_iter, n_restarts=stage.restarts) \
            if self.wanted and stage.selection == "per_demonstration" else None
        self._stack = contextlib.ExitStack()
        self.work_map = None
        self._map = None  # the pool's map, done in this process once the pool is broken (a worker killed)
        self._pending: dict[str, object] = {}
        self.fitted: dict[tuple, object] = {}  # job key -> the model fitted ahead

    def read(self, path: str) -> None:
        """Start reading the recording at ``path`` (a pool's map submits at once)."""
        if not self.wanted:
            return
        if self.work_map is None:
            self.work_map = self._stack.enter_context(process_map(self._workers))
            self._map = FallbackMap(self.work_map, self._say, POOL)
        if self.work_map is not map:  # one CPU: the builtin map, which would read it only when asked
            self._pending[path] = self._map(self._load, [path]) if self._vote is None else \
                self._map(_read_and_vote, [(self._load, path, self._vote)])

    @property
    def pending(self) -> tuple:
        """The recordings whose reading has started and not been taken yet."""
        return tuple(self._pending)

    def demonstrations(self, paths: list[str]) -> list[dict]:
        """The recordings at ``paths``, read: those started already, the others now."""
        demos = []
        for p in paths:
            if p not in self._pending:
                demos.append(next(self._map(self._load, [p])))
                continue
            got = next(self._pending.pop(p))
            if self._vote is not None:
                got, fits = got
                self.fitted.update(fits)
            demos.append(got)
        return demos

    def fit_map(self, fn, jobs):
        """The pool's ``map`` for the vote's fits: a fit already done ahead is taken, the
        others run now, in order."""
        jobs = list(jobs)
        ahead = [self.fitted.pop(_job_key(j), None) if fn is fit_candidate else None for j in jobs]
        missing = [j for j, model in zip(jobs, ahead) if model is None]
        rest = self._map(fn, missing) if missing else iter(())
        for model in ahead:
            yield next(rest) if model is None else model

    def close(self) -> None:
        """The pool's work is done: its workers exit; later demonstrations are not read ahead."""
        self._pending.clear()
        self.fitted.clear()
        self._stack.close()
        self.wanted, self.work_map, self._map = False, None, None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._pending.clear()
        return self._stack.__exit__(*exc)


def learn(stage: LearnStage, scenario: Scenario, demonstrations: list[str], out: Path, *, workers: int | None = None,
          threads: int | None = None, say=print, reads: DemonstrationReads | None = None) -> LearningRecord:
    """Fit the stage's model(s) to the recordings ``demonstrations`` and save them in ``out``
    (``model.json``, the run's; ``model-STAR.json`` beside it when both are learned).
    ``reads``: the pool that started reading them during the demonstrations, if any."""
    record = LearningRecord()
    t = time.monotonic()
    started = reads is not None and reads.work_map is not None
    # choosing the number of phases is many independent fits: worth a pool of processes,
    # which then reads the demonstrations too (a fixed number of phases is one fit)
    # (the pool that read them during the demonstrations, through its own FallbackMap, when it did)
    with (contextlib.nullcontext() if started else process_map(workers if stage.phases == "auto" else 1)) as pool:
        if started:
            demos, fit_map = reads.demonstrations(demonstrations), reads.fit_map
        else:
            fit_map = FallbackMap(pool, say, POOL)
            demos = list(fit_map(_reader(scenario), demonstrations))
        record.learned_from = [dict(path=path, samples=len(d["states"])) for path, d in zip(demonstrations, demos)]
        record.demonstrations = demos
        with learning_threads(threads):
            models, selection = _fit(stage, demos, fit_map, say)
    if started:
        reads.close()  # learned: the pool's work is done (on a failure the run's exit terminates it)
    for i, m in enumerate(models):
        # which learned phase is which true phase is judged on the demonstrations only
        task = learn_task(m, demos, float(demos[0]["dt"]), state=scenario.state, features=scenario.features,
                          state_resolution=scenario.state_resolution, selection=selection, sources=[d["path"] for d in demos])
        name = MODEL_NAMES[m.transitions]
        # a later scenario can reproduce with this file alone
        path = write_via(out / ("model.json" if i == 0 else f"model-{name}.json"), task.save)
        record.models[m.transitions] = ModelRecord(name=name, path=str(path), goal=task.goal.tolist(),
                                                   phase_to_truth=task.phase_to_truth)
        if i == 0:
            record.adopt(record.models[m.transitions], task.selection)
    if len(models) > 1:
        record.offline = _score_offline(models, demos, stage.seed, say)
    record.seconds = time.monotonic() - t
    say(f"learned {models[0].n_phases} phases in {record.seconds:.1f} s; model {record.model_path}")
    return record


def _fit(stage: LearnStage, demos: list[dict], work_map, say) -> tuple[list, dict]:
    """The fitted models, the run's first, and how its number of phases was chosen."""
    pairs = [(d["states"], d["forces"]) for d in demos]
    options = dict(n_restarts=stage.restarts)
    first, *others = stage.transitions
    if stage.phases == "auto":
        # each candidate fit says `fit i/N done` as it comes back from the pool
        say(f"learning: {stage.criterion.upper()} over {list(stage.candidates)} phases from "
            f"{len(pairs)} demonstrations ({sum(len(s) for s, _ in pairs)} samples)")
        model, selection = fit_order(pairs, stage.candidates, stage.criterion, stage.selection, transitions=first,
                                     seed=stage.seed, max_iter=stage.max_iter, progress=say, fit_map=work_map,
                                     **options)
    else:
        say(f"learning: {int(stage.phases)} phases from {len(pairs)} demonstrations "
            f"({sum(len(s) for s, _ in pairs)} samples)")
        model = ETAR(int(stage.phases), first, **options).fit(pairs, max_iter=stage.max_iter, seed=stage.seed,
                                                              progress=say)
        selection = dict(criterion="fixed", best=int(stage.phases), scores={}, log_likelihoods={
            str(stage.phases): model.fit_report_.log_likelihood}, n_parameters={})
    models = [model]
    for transitions in others:
        # the comparison is between transition models, so the number of phases is the first's
        say(f"learning: {MODEL_NAMES[transitions]} with {model.n_phases} phases on the same demonstrations")
        models.append(ETAR(model.n_phases, transitions, **options).fit(pairs, max_iter=stage.max_iter,
                                                                       seed=stage.seed, progress=say))
    return models, selection


def _score_offline(models, demos, seed: int, say) -> list[dict]:
    """Each model's Viterbi and online filter against the demonstrations' true phases."""
    pairs = [(d["states"], d["forces"]) for d in demos]
    truths = [d["phases"] for d in demos]
    scores = []
    for m in models:
        e = evaluate(m, pairs, truths, float(demos[0]["dt"]), seed=seed)
        scores.append(dict(model=MODEL_NAMES[m.transitions], **e.to_dict()))
        say(f"offline, {MODEL_NAMES[m.transitions]}: filter accuracy {e.filtered.accuracy:.4f}, Viterbi "
            f"{e.viterbi.accuracy:.4f}, {e.filtered.spurious_switches} spurious switches, "
            f"one-step error near transitions {e.error_near_transitions:.3g}")
    return scores


def stored_model(scenario: Scenario, task, say=print) -> LearningRecord:
    """The scenario's ``model`` file as the run's model: ``task``, loaded and checked
    against the scenario before anything started (``services.run.preflight``)."""
    path = scenario.model_path()
    record = LearningRecord()
    record.adopt(ModelRecord(name=None, path=str(path), goal=task.goal.tolist(), phase_to_truth=task.phase_to_truth),
                 task.selection)
    say(f"model {path}: {task.n_phases} phases, goal {np.round(task.goal, 3).tolist()}")
    return record
