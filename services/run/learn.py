"""The learn stage: ETAR (and STAR, for the comparison) fitted to the recorded demonstrations,
the number of phases chosen by BIC/AIC or fixed, every phase's impedance derived, the
models saved; or a scenario's stored model, checked against the scenario."""

from __future__ import annotations

import functools
import time
from pathlib import Path

import numpy as np

from etar import ETAR
from etar.comparison import MODEL_NAMES, evaluate
from etar.selection import fit_order
from etar.task import learn_task
from services.recordings.demonstrations import load_demonstration
from services.results.record import LearningRecord, ModelRecord
from services.runtime.files import write_via
from services.runtime.threads import learning_threads, process_map
from services.scenario import LearnStage, Scenario


def learn(stage: LearnStage, scenario: Scenario, demonstrations: list[str], out: Path, *, workers: int | None = None,
          threads: int | None = None, say=print) -> LearningRecord:
    """Fit the stage's model(s) to the recordings ``demonstrations`` and save them in ``out``
    (``model.json``, the run's; ``model-STAR.json`` beside it when both are learned)."""
    record = LearningRecord()
    t = time.monotonic()
    # choosing the number of phases is many independent fits: worth a pool of processes,
    # which then reads the demonstrations too (a fixed number of phases is one fit)
    with process_map(workers if stage.phases == "auto" else 1) as work_map:
        demos = list(work_map(functools.partial(load_demonstration, state=scenario.state,
                                                features=scenario.features,
                                                state_resolution=scenario.state_resolution), demonstrations))
        record.learned_from = [dict(path=path, samples=len(d["states"])) for path, d in zip(demonstrations, demos)]
        with learning_threads(threads):
            models, selection = _fit(stage, demos, work_map, say)
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
