"""The thesis' figures (section 6) of a run: ``etar-bench figures RUN_DIR``.

Every run writes them into ``RUN_DIR/figures/`` too.  One PNG per figure, titled,
axes labelled with units, named after what it shows, drawn by the module of its family:

- ``demonstrations_position_and_force.png`` (``demonstrations``): each demonstration's
  tool position and contact force over time (thesis fig. 13, 21);
- ``bic_by_phase_count.png`` (``learning``): the selection criterion against the number
  of phases, per demonstration and pooled (fig. 14, 22);
- ``forward_variable_demonstrations.png`` (``learning``): the normalised forward variable
  alpha over each demonstration, the true phase boundaries dashed (fig. 15a, 23, 24a);
- ``tool_path_by_phase.png`` (``tool_paths``): the tool path in 3-D coloured by the
  estimated (Viterbi) phase, on the task's surfaces (the valley's plates, the coupler's
  socket), each path's start (circle) and end (cross), the learned goal (star), equal
  axes, seen across its motion (fig. 15b, 24b);
- ``prediction_error_by_step.png`` (``learning``): per step of the first demonstration,
  the one-step prediction error of every phase's parameters, true boundaries dashed
  (fig. 16-19, 28b/c);
- ``prediction_error_by_phase.png`` (``learning``): the K x K bars E_rho_i(theta_j)
  (fig. 20, 29);
- ``reproduction_NN_force_phase_alpha.png`` (``reproduction``; the first reproduction):
  the force feature, the estimated phase beside the true phase it is scored against,
  and alpha over time, with the commanded phase switches (fig. 25).

Phases are named by what they are where the run knows it (``phases``): a learned phase k
that the demonstrations matched to a true phase (the model's ``phase_to_truth``) is
"phase k = <the labeller's name of that true phase>" (robot_sim.labels), else "phase k".
Data stay SI; a figure shows positions in mm (its axis says so), forces in N, time in s
(``canvas``).

What a figure needs and the run does not have (no demonstrations, a fixed phase count:
no selection scores) is skipped with the reason.  Drawn right after a run's report from
what the report decoded (the run's record), or from a finished run's folder: its
report.json, scenario.yaml, model.json and recordings, each decoded as the report decodes
them (``services.results.decoding``).  A run whose recordings are worth a process beside
it draws those that need no reproduction there while it reproduces (``learning_figures``,
from the learner's arrays: the same files).  Writes nothing but the figures.
"""

from __future__ import annotations

from pathlib import Path

from etar.task import LearnedTask, load_task
from services.results.decoding import EpisodeReading, FigureData, LearnerView, decode_episode
from services.results.figures.demonstrations import demonstrations_figure
from services.results.figures.learning import bic_figure, forward_figure, prediction_figures
from services.results.figures.phases import phase_labels, true_phase_names, world_of_run
from services.results.figures.reproduction import reproduction_figure
from services.results.figures.tool_paths import path_figure
from services.results.folder import RunFolderError, kept_recordings, read_report, report_episodes
from services.results.record import RunRecord

FIGURES_DIR = "figures"
# etar-bench compare's figure (services.results.compare), beside the run's own: not the run's to redraw
COMPARISON_FIGURE = "etar_vs_star_phases.png"


class FiguresError(ValueError):
    """A run directory the figures cannot be drawn from (names the file)."""


def in_run(run_dir: Path, path) -> Path:
    """A path report.json names: relative to the run's folder unless absolute."""
    return Path(path) if Path(path).is_absolute() else run_dir / path


def read_run_report(run_dir: Path) -> dict:
    """A finished run's report.json; FiguresError naming the file if there is none."""
    try:
        report = read_report(run_dir)
    except RunFolderError as exc:
        raise FiguresError(str(exc)) from None
    path = Path(run_dir) / "report.json"
    if "learning" not in report:
        raise FiguresError(f"{path}: not a run report (no 'learning')")
    if not isinstance(report["learning"], dict):
        raise FiguresError(f"{path}: learning: expected an object, got {type(report['learning']).__name__}")
    for kind in ("demonstrations", "reproductions"):
        try:
            episodes = report_episodes(report, kind, path)
        except RunFolderError as exc:
            raise FiguresError(str(exc)) from None
        if not all(isinstance(e, dict) and isinstance(e.get("path"), str) for e in episodes):
            raise FiguresError(f"{path}: {kind}: expected each episode with its recording's path")
    return report


def write_figures(run_dir, progress=None, run: RunRecord | None = None,
                  ahead: tuple | None = None) -> tuple[list[Path], list[str], list[str]]:
    """Every figure the run has data for, into RUN_DIR/figures/: (files written, what was
    skipped and why, the recordings that were damaged: unreadable, or cut and drawn from
    what they hold).  ``run``: the record of the run just reported, whose report and
    recordings, as the report decoded them, the figures draw; None: the folder's
    report.json, and its recordings decoded here.  ``ahead``: ``learning_figures``' result
    for this run (drawn while it reproduced): only the reproduction's figure is left."""
    run_dir = Path(run_dir)
    report = read_run_report(run_dir) if run is None else run.report
    out = run_dir / FIGURES_DIR
    out.mkdir(exist_ok=True)
    model_path = report["learning"].get("model")
    if not model_path:
        return [], ["no learned model in the run"], []
    task = load_task(in_run(run_dir, model_path))
    if run is not None and run.figures is not None:
        first = run.reproductions[0].figure_data if run.reproductions else None
        world, demos = run.world, [d.figure_data for d in run.demonstrations]
    else:
        world, demos, first = _decoded(run_dir, report, task)
    return _draw(task, world, report, demos, first, out, progress or (lambda _m: None), ahead)


def _decoded(run_dir: Path, report: dict, task: LearnedTask) -> tuple[str | None, list, FigureData | None]:
    """What the figures draw of a finished run's folder: its world, each demonstration's
    data and the first reproduction's, each recording decoded as the model sees it."""
    view = LearnerView(task.state, task.features, task.state_resolution)
    demonstrations, reproductions = report.get("demonstrations", []), report.get("reproductions") or []
    recordings = [in_run(run_dir, e["path"]) for e in [*demonstrations, *reproductions] if e.get("path")]
    world = world_of_run(run_dir, recordings[:1])
    if not kept_recordings(run_dir):  # none kept by choice: the figures of the report alone
        return world, [], None

    def decoded(entry: dict, **what) -> FigureData:
        parts = tuple(str(in_run(run_dir, p)) for p in entry.get("recording_parts") or ())
        return decode_episode(EpisodeReading(str(in_run(run_dir, entry["path"])), parts, measures=False,
                                             **what)).figure_data

    first = decoded(reproductions[0], trace=view) if reproductions else None
    return world, [decoded(d, demonstration=view) for d in demonstrations], first


def _draw(task: LearnedTask, world, report: dict, demos_data: list, first: FigureData | None, out: Path,
          say, ahead: tuple | None = None) -> tuple[list[Path], list[str], list[str]]:
    """Every figure; ``ahead``: what ``learning_figures`` drew already (then only the reproduction's)."""
    if ahead is None:
        ahead = _draw_learning(task, world, [d["path"] for d in report.get("demonstrations", [])], demos_data,
                               report["learning"].get("selection") or {}, out, say)
    written, skipped, damaged = (list(part) for part in ahead)
    damaged += [p for p in ((first.problem, first.cut) if first is not None else ()) if p]
    repro = report.get("reproductions") or []
    if repro and first is None:
        skipped.append("the run kept no recordings: the reproduction's figure is not drawn")
    elif repro:
        names = true_phase_names(world)
        # the mapping the report scored this reproduction with, else the model's
        mapping = (repro[0].get("phases") or {}).get("mapping") or task.phase_to_truth
        fig = (f"reproduction 0: {first.problem}" if first.problem is not None else
               reproduction_figure(first.trace, 0, task.model, out, phase_to_truth=mapping, true_names=names))
        (written if isinstance(fig, Path) else skipped).append(fig)
    return written, skipped, damaged


def learning_figures(run_dir, model_path: str, world, demonstrations: list[str], arrays: list[dict],
                     selection: dict | None) -> tuple[list[Path], list[str], list[str]]:
    """The figures of the demonstrations and the learning (all but the reproduction's) from the
    demonstrations as the learner read them (``demonstrations``: their recordings' paths):
    what a run draws beside its reproductions, its report's figures then adding the
    reproduction's (``write_figures``' ``ahead``).  As ``write_figures``, its share."""
    out = Path(run_dir) / FIGURES_DIR
    out.mkdir(exist_ok=True)
    task = load_task(in_run(Path(run_dir), model_path))
    return _draw_learning(task, world, demonstrations, [FigureData(arrays=a) for a in arrays], selection or {}, out,
                          lambda _m: None)


def _draw_learning(task: LearnedTask, world, paths: list[str], demos_data: list, selection: dict, out: Path,
                   say) -> tuple[list[Path], list[str], list[str]]:
    """The demonstrations' and the learning's figures (all but the reproduction's)."""
    model = task.model
    labels = phase_labels(model.n_phases, task.phase_to_truth, true_phase_names(world))
    written, skipped, demos = [], [], []
    damaged = [p for data in demos_data for p in (data.problem, data.cut) if p]
    for path, data in zip(paths, demos_data):
        if data.problem is None:
            demos.append(data.arrays)
        else:
            skipped.append(f"demonstration {Path(path).name}: {data.problem}")
    if demos:
        say(f"figures: {len(demos)} demonstrations")
        written.append(demonstrations_figure(demos, out))
        written.append(forward_figure(model, demos, out, labels))
        written.append(path_figure(model, demos, out, labels, world=world, goal=task.goal))
        written += prediction_figures(model, demos, out, labels)
    elif paths and not demos_data:
        skipped.append("the run kept no recordings: the demonstrations' figures are not drawn")
    else:
        skipped.append("no demonstrations: their figures are not drawn")
    bic = bic_figure(selection, out)
    (written if isinstance(bic, Path) else skipped).append(bic)
    return written, skipped, damaged
