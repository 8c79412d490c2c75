"""The thesis' figures (section 6) from a finished run: ``etar-bench figures RUN_DIR``.

Every run writes them into ``RUN_DIR/figures/`` too.  One PNG per figure, titled,
axes labelled with units, named after what it shows:

- ``demonstrations_position_and_force.png``: each demonstration's tool position
  and contact force over time (thesis fig. 13, 21);
- ``bic_by_phase_count.png``: the selection criterion against the number of
  phases, per demonstration and pooled (fig. 14, 22);
- ``forward_variable_demonstrations.png``: the normalised forward variable alpha
  over each demonstration, the true phase boundaries dashed (fig. 15a, 23, 24a);
- ``tool_path_by_phase.png``: the tool path in 3-D coloured by the estimated
  (Viterbi) phase, on the task's surfaces (the valley's plates, the coupler's
  socket), each path's start (circle) and end (cross), the learned goal (star),
  equal axes, seen across its motion (fig. 15b, 24b);
- ``prediction_error_by_step.png``: per step of the first demonstration, the
  one-step prediction error of every phase's parameters, true boundaries dashed
  (fig. 16-19, 28b/c);
- ``prediction_error_by_phase.png``: the K x K bars E_rho_i(theta_j) (fig. 20, 29);
- ``reproduction_NN_force_phase_alpha.png`` (the first reproduction): the force
  feature, the estimated phase beside the true phase it is scored against, and
  alpha over time, with the commanded phase switches (fig. 25).

Phases are named by what they are where the run knows it: a learned phase k that
the demonstrations matched to a true phase (the model's ``phase_to_truth``) is
"phase k = <the labeller's name of that true phase>" (robot_sim.world.labels), else
"phase k".  Data stay SI; a figure shows positions in mm (its axis says so),
forces in N, time in s.

What a figure needs and the run does not have (no demonstrations, a fixed phase
count: no selection scores) is skipped with the reason.  Reads the run's
report.json, scenario.yaml, model.json and recordings; writes nothing else.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np

from etar.analysis import prediction_errors
from etar.comparison import filtered_messages
from etar.metrics import score_segmentation
from etar.task import load_task
from robot_sim.world.labels import LABELERS
from robot_sim.world.tasks import HoseCoupler, Valley
from services.recordings.demonstrations import load_demonstration
from services.recordings.reader import read_episode
from services.results.folder import RunFolderError, read_report
from services.runtime.messages import loads
from services.runtime.files import write_via

FIGURES_DIR = "figures"
# etar-bench compare's figure (services.results.compare), beside the run's own: not the run's to redraw
COMPARISON_FIGURE = "etar_vs_star_phases.png"
MM = 1e3  # m -> mm, for the axes that say [mm]
UNMATCHED = (0.8, 0.8, 0.8, 1.0)  # a true phase no learned phase was matched to


class FiguresError(ValueError):
    """A run directory the figures cannot be drawn from (names the file)."""


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _phase_colors(k: int):
    plt = _plt()
    return [plt.get_cmap("tab10")(i % 10) for i in range(k)]


def _boundaries(labels) -> list:
    labels = np.asarray(labels)
    return list(np.flatnonzero(np.diff(labels)) + 1)


def _save(fig, path: Path, laid_out: bool = False) -> Path:
    """Write ``fig`` to ``path`` and let it go.  ``laid_out``: the axes were placed by hand
    (tight_layout misjudges 3-D axes): crop the picture to what is drawn instead."""
    if not laid_out:
        fig.tight_layout()
    try:
        crop = dict(bbox_inches="tight", pad_inches=0.15) if laid_out else {}
        write_via(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png", **crop))
    finally:
        _plt().close(fig)
    return path


# ------------------------------------------------------------------ what the phases are


def true_phase_names(world) -> tuple:
    """The labeller's names of the true phases of ``world`` (() for a world without a task)."""
    labeler = LABELERS.get(world) if isinstance(world, str) else None
    return tuple(labeler.names) if labeler is not None else ()


def phase_labels(n_phases: int, phase_to_truth=None, true_names=()) -> list[str]:
    """One legend label per learned phase: "phase k = <true name>" where the mapping
    says which true phase k is and the world names it, else "phase k"."""
    mapping = {int(k): int(v) for k, v in (phase_to_truth or {}).items()}
    labels = []
    for k in range(n_phases):
        v = mapping.get(k)
        labels.append(f"phase {k} = {true_names[v]}" if v is not None and 0 <= v < len(true_names) else f"phase {k}")
    return labels


def _true_label(v: int, true_names) -> str:
    return f"{true_names[v]} (true phase {v})" if 0 <= v < len(true_names) else f"true phase {v}"


def world_of_scenario(text) -> str | None:
    """The ``world:`` of a scenario's YAML text, None if it has none or does not parse."""
    if not text:
        return None
    import yaml

    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return None
    world = value.get("world") if isinstance(value, dict) else None
    return world if isinstance(world, str) else None


def world_of_run(run_dir: Path, recordings=()) -> str | None:
    """The run's task world: its scenario.yaml's, else the first recording's attached scenario's."""
    try:
        world = world_of_scenario((Path(run_dir) / "scenario.yaml").read_text())
    except OSError:
        world = None
    for path in recordings:
        if world is not None:
            break
        world = world_of_recording(path)
    return world


def world_of_recording(path) -> str | None:
    try:
        return world_of_scenario(read_episode(path).scenario_text)
    except (OSError, ValueError):
        return None


# ------------------------------------------------------------------ 3-D tool paths


def _sample_phases(step_phases, n_samples: int) -> np.ndarray:
    """One phase per sample from one per step (step t -> t+1 labels sample t+1; sample 0 takes the first step's)."""
    step_phases = np.asarray(step_phases, dtype=int)
    if len(step_phases) == 0:
        return np.zeros(n_samples, dtype=int)
    return np.concatenate([step_phases[:1], step_phases])[:n_samples]


def _bounds(points: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    return points.min(axis=0) - margin, points.max(axis=0) + margin


def _valley_surfaces(g: Valley, lo: np.ndarray, hi: np.ndarray, margin: float) -> list:
    """The two plates' top surfaces (m) over the paths' stretch of groove, far enough up
    each side that the V shows (both plates, however far the paths climbed one)."""
    x0, x1 = max(g.x_start, lo[0]), min(g.x_end, hi[0])
    if x0 >= x1:  # the paths are off the valley's ends: show its nearest stretch
        x0, x1 = (g.x_start, min(g.x_end, g.x_start + 2 * margin)) if hi[0] < g.x_start else \
                 (max(g.x_start, g.x_end - 2 * margin), g.x_end)
    reach = min(g.half_width, max(abs(lo[1]), abs(hi[1]), 2 * margin))
    top = g.surface_z(reach)
    polys = []
    for side in (-1, 1):
        y = side * reach
        polys.append([(x0, 0.0, g.groove_z), (x1, 0.0, g.groove_z), (x1, y, top), (x0, y, top)])
    return polys


def _coupler_surfaces(g: HoseCoupler, n: int = 32) -> list:
    """The socket (m): its floor, the bore's wall and the wall's outside and rim."""
    cx, cy, cz = g.center
    wall = 0.01
    r_in, r_out = g.bore_radius, g.bore_radius + wall
    a = np.linspace(0.0, 2 * math.pi, n + 1)

    def ring(r, z):
        return [(cx + r * math.cos(t), cy + r * math.sin(t), z) for t in a]

    polys = [ring(r_out, cz)[:-1]]  # floor
    top = cz + g.depth
    for r in (r_in, r_out):
        lower, upper = ring(r, cz), ring(r, top)
        polys += [[lower[i], lower[i + 1], upper[i + 1], upper[i]] for i in range(n)]
    inner, outer = ring(r_in, top), ring(r_out, top)
    polys += [[inner[i], inner[i + 1], outer[i + 1], outer[i]] for i in range(n)]
    return polys


def task_surfaces(world, lo: np.ndarray, hi: np.ndarray, margin: float) -> list:
    """Polygons (lists of (x, y, z) in m) of ``world``'s task geometry near the box lo..hi (m)."""
    if world == "valley":
        return _valley_surfaces(Valley(), lo, hi, margin)
    if world == "hose_coupler":
        return _coupler_surfaces(HoseCoupler())
    return []


def view_angles(points: np.ndarray, world=None) -> tuple[float, float]:
    """(elevation, azimuth) in degrees for a 3-D view of ``points`` (N, 3): looking along
    the direction in which they vary least (so their motion spreads across the picture),
    from above (elevation 20..40 deg); in the valley from near the groove's axis (azimuth
    within 40 deg of it) so that the V of the two plates shows."""
    pts = np.asarray(points, dtype=float)
    if len(pts) < 3 or not np.all(np.isfinite(pts)):
        return 30.0, -60.0
    _, vecs = np.linalg.eigh(np.cov((pts - pts.mean(axis=0)).T))
    v = vecs[:, 0]
    if v[2] < 0:
        v = -v
    elev = float(np.clip(math.degrees(math.asin(min(1.0, abs(v[2])))), 20.0, 40.0))
    azim = math.degrees(math.atan2(v[1], v[0])) if math.hypot(v[0], v[1]) > 1e-9 else -60.0
    if world == "valley":
        # the groove runs along x: from the end of the groove the azimuth is near 0 or 180
        if abs(azim) <= 90:
            azim = float(np.clip(azim, -40.0, 40.0))
        else:
            azim = float(np.clip(azim % 360.0, 140.0, 220.0))
    return elev, azim


def draw_paths_3d(ax, paths, phases, colors, labels, *, world=None, goal=None) -> None:
    """The tool paths (each (T, 3) m, drawn in mm) coloured by ``phases`` (one per sample),
    on the task's surfaces, each path's start (filled circle) and end (cross), ``goal`` (m,
    a star) if known; equal axes, seen across the motion."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    pts = np.vstack([np.asarray(p, dtype=float)[:, :3] for p in paths])
    if goal is not None:
        pts = np.vstack([pts, np.asarray(goal, dtype=float)[None, :3]])
    span = float(np.max(np.ptp(pts, axis=0))) if len(pts) else 0.0
    margin = max(0.01, 0.1 * span)
    lo, hi = _bounds(pts, margin)
    polys = task_surfaces(world, lo, hi, margin)
    ax.computed_zorder = False  # the paths lie on the surfaces: draw them over, not behind
    ax.set_autoscale_on(False)  # the limits are set below, from the paths and the surfaces
    if polys:
        surf = Poly3DCollection([np.asarray(p) * MM for p in polys], facecolor=(0.62, 0.66, 0.72, 0.35),
                                edgecolor=(0.35, 0.38, 0.42, 0.6), linewidth=0.4, zorder=0)
        surf.set_label({"valley": "valley plates", "hose_coupler": "coupler socket"}.get(world, "task surfaces"))
        ax.add_collection3d(surf)
        corners = np.vstack([np.asarray(p) for p in polys])
        lo, hi = np.minimum(lo, corners.min(axis=0)), np.maximum(hi, corners.max(axis=0))
    for p, ph in zip(paths, phases):
        p = np.asarray(p, dtype=float)[:, :3] * MM
        ph = np.asarray(ph, dtype=int)
        cuts = [0, *_boundaries(ph), len(ph)]
        for a, b in itertools.pairwise(cuts):
            seg = p[max(0, a - 1):b]  # from the last sample of the previous run: the path stays joined
            ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color=colors[ph[a]], lw=2.0, zorder=2)
    for k, label in enumerate(labels):
        if label is not None:  # None: a phase left out of the legend
            ax.plot([], [], [], color=colors[k], lw=2.5, label=label)
    starts = np.array([np.asarray(p, dtype=float)[0, :3] for p in paths]) * MM
    ends = np.array([np.asarray(p, dtype=float)[-1, :3] for p in paths]) * MM
    ax.scatter(starts[:, 0], starts[:, 1], starts[:, 2], marker="o", s=45, color="black", depthshade=False,
               zorder=3, label="start")
    ax.scatter(ends[:, 0], ends[:, 1], ends[:, 2], marker="X", s=70, color="black", edgecolor="white",
               linewidth=0.6, depthshade=False, zorder=3, label="end")
    if goal is not None:
        g = np.asarray(goal, dtype=float)[:3] * MM
        # hollow: the paths' ends (crosses) lie at the goal, their mean
        ax.scatter([g[0]], [g[1]], [g[2]], marker="*", s=420, facecolor="none", edgecolor="darkgoldenrod",
                   linewidth=1.6, depthshade=False, zorder=4, label="goal (learned: mean end)")
    lo_mm, hi_mm = lo * MM, hi * MM
    ax.set_xlim(lo_mm[0], hi_mm[0])
    ax.set_ylim(lo_mm[1], hi_mm[1])
    ax.set_zlim(lo_mm[2], hi_mm[2])
    ax.set_box_aspect(tuple(np.maximum(hi_mm - lo_mm, 1e-3)))  # equal scale on the three axes
    ax.set_proj_type("ortho")
    ax.view_init(*view_angles(pts, world))
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")


# ------------------------------------------------------------------ the figures


def demonstrations_figure(demos, out: Path) -> Path:
    plt = _plt()
    torque = all(d["forces"].shape[1] >= 6 for d in demos)  # force_torque features: the turn shows in the torque
    rows = 3 if torque else 2
    fig, axes = plt.subplots(rows, 3, figsize=(12, 3 * rows), sharex=True)
    for i, d in enumerate(demos):
        t = d["t"] - d["t"][0]
        for a in range(3):
            axes[0, a].plot(t, d["states"][:, a] * MM, lw=1, label=f"demonstration {i}")
            axes[1, a].plot(t, d["forces"][:, a], lw=1)
            if torque:
                axes[2, a].plot(t, d["forces"][:, 3 + a], lw=1)
    for a, name in enumerate("xyz"):
        axes[0, a].set_title(f"tool position {name}")
        axes[0, a].set_ylabel(f"{name} [mm]")
        axes[1, a].set_title(f"contact force F{name}")
        axes[1, a].set_ylabel(f"F{name} [N]")
        if torque:
            axes[2, a].set_title(f"contact torque T{name}")
            axes[2, a].set_ylabel(f"T{name} [N m]")
        axes[-1, a].set_xlabel("time [s]")
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    what = "contact force and torque" if torque else "contact force"
    fig.suptitle(f"Demonstrations: tool position and {what}, base axes (thesis fig. 13, 21)")
    return _save(fig, out / "demonstrations_position_and_force.png")


def demonstration_figure(demo: dict, path: Path, title: str = "", phase_names=(), world=None) -> Path:
    """One demonstration (``load_demonstration``'s arrays): the 3-D tool path coloured by the
    true phase on the task's surfaces, beside the tool position and the (tared) force in
    base axes over time (thesis fig. 13 and 15b).  ``world``: the task world (default: the
    one in the recording's scenario, if ``demo`` names its recording)."""
    plt = _plt()
    p, t = demo["states"][:, :3], demo["t"] - demo["t"][0]
    ph = _sample_phases(demo["phases"], len(p))
    if world is None and demo.get("path"):
        world = world_of_recording(demo["path"])
    names = list(phase_names) or list(true_phase_names(world))
    n = max(int(ph.max()) + 1, len(names))
    labels = [names[k] if k < len(names) else f"true phase {k}" for k in range(n)]
    colours = _phase_colors(n)
    fig = plt.figure(figsize=(13, 5.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    present = set(ph.tolist())
    draw_paths_3d(ax, [p], [ph], colours, [label if k in present else None for k, label in enumerate(labels)],
                  world=world)
    ax.legend(loc="center left", bbox_to_anchor=(0.98, 0.5), fontsize=8)
    ax.set_title(title or "tool path (tip centre), coloured by true phase")
    axp = fig.add_subplot(2, 2, 2)
    axf = fig.add_subplot(2, 2, 4, sharex=axp)
    for i, c in enumerate("xyz"):
        axp.plot(t, p[:, i] * MM, label=c)
        axf.plot(t, demo["forces"][:, i], label=f"F{c}")
    for ax_ in (axp, axf):
        for b in _boundaries(ph):
            ax_.axvline(t[b], color="k", lw=0.8, ls="--")
        ax_.legend(loc="upper right", fontsize=8)
        ax_.grid(alpha=0.3)
    axp.set_ylabel("tool position [mm]")
    axf.set_ylabel("force on tool [N]")
    axf.set_xlabel("time [s]  (dashed: true phase changes)")
    return _save(fig, Path(path))


def bic_figure(selection: dict, out: Path) -> Path | str:
    per = selection.get("per_demonstration") or []
    pooled = selection.get("scores") or {}
    if not per and not pooled:
        return f"no selection scores (phase count {selection.get('criterion', 'fixed')})"
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    crit = str(selection.get("criterion", "bic")).upper()
    for i, d in enumerate(per):
        ks = sorted(d["scores"], key=int)
        ax.plot([int(k) for k in ks], [d["scores"][k] for k in ks], "o-", lw=1, ms=3, label=f"demonstration {i}")
    if pooled:
        ks = sorted(pooled, key=int)
        ax.plot([int(k) for k in ks], [pooled[k] for k in ks], "ks-", lw=2, label="pooled")
    ax.axvline(selection["best"], color="grey", ls="--", lw=1, label=f"chosen: {selection['best']}")
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_xlabel("number of phases K [-]")
    ax.set_ylabel(f"{crit} [-] (lower is better)")
    ax.set_title(f"{crit} against the number of phases\n(thesis fig. 14, 22)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return _save(fig, out / "bic_by_phase_count.png")


def forward_figure(model, demos, out: Path, labels=None) -> Path:
    plt = _plt()
    colors = _phase_colors(model.n_phases)
    labels = labels or phase_labels(model.n_phases)
    fig, axes = plt.subplots(len(demos), 1, figsize=(10, 1.8 * len(demos) + 1.4), sharex=False, squeeze=False)
    for i, d in enumerate(demos):
        ax = axes[i, 0]
        alpha = filtered_messages(model, d["states"], d["forces"])
        t = d["t"][1:] - d["t"][0]
        for k in range(model.n_phases):
            ax.plot(t, alpha[:, k], color=colors[k], lw=1.2, label=labels[k])
        for b in _boundaries(d["phases"]):
            ax.axvline(t[b], color="black", ls="--", lw=0.8)
        ax.set_ylim(-0.05, 1.05)
        ax.set_ylabel(f"demo {i}\nalpha [-]")
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=8, ncol=min(model.n_phases, 4), loc="lower center", bbox_to_anchor=(0.5, 1.0),
                      frameon=False)
    fig.suptitle("Normalised forward variable over each demonstration; dashed: true phase boundaries "
                 "(thesis fig. 15a, 23, 24a)")
    return _save(fig, out / "forward_variable_demonstrations.png")


def path_figure(model, demos, out: Path, labels=None, world=None, goal=None) -> Path:
    plt = _plt()
    colors = _phase_colors(model.n_phases)
    labels = labels or phase_labels(model.n_phases)
    fig = plt.figure(figsize=(10, 7))
    ax = fig.add_axes((0.0, 0.02, 0.72, 0.86), projection="3d")
    paths, phases = [], []
    for d in demos:
        paths.append(d["states"][:, :3])
        phases.append(_sample_phases(model.viterbi(d["states"], d["forces"]), len(d["states"])))
    draw_paths_3d(ax, paths, phases, colors, labels, world=world, goal=goal)
    fig.legend(*ax.get_legend_handles_labels(), fontsize=8, loc="center left", bbox_to_anchor=(0.7, 0.5))
    where = {"valley": " in the valley", "hose_coupler": " at the hose coupler"}.get(world, "")
    fig.suptitle(f"Demonstrated tool paths{where}, coloured by the estimated (Viterbi) phase\n"
                 "circle: start, cross: end (thesis fig. 15b, 24b)")
    return _save(fig, out / "tool_path_by_phase.png", laid_out=True)


def prediction_figures(model, demos, out: Path, labels=None) -> list[Path]:
    plt = _plt()
    colors = _phase_colors(model.n_phases)
    K = model.n_phases
    labels = labels or phase_labels(K)
    d = demos[0]
    s, f = d["states"], d["forces"]
    A, B = np.asarray(model.A), np.asarray(model.B)
    u = np.hstack([f[:-1], np.ones((len(s) - 1, 1))])
    t = d["t"][1:] - d["t"][0]
    fig, axes = plt.subplots(K, 1, figsize=(10, 1.9 * K + 1), sharex=True, squeeze=False)
    for j in range(K):
        # the position part of the state (a pose's turn is in rad, not mm)
        err = np.linalg.norm((s[:-1] @ A[j].T + u @ B[j].T - s[1:])[:, :3], axis=1) * MM
        axes[j, 0].bar(t, err, width=(t[1] - t[0]) if len(t) > 1 else 0.01, color=colors[j])
        for b in _boundaries(d["phases"]):
            axes[j, 0].axvline(t[b], color="black", ls="--", lw=0.8)
        axes[j, 0].set_ylabel(f"theta_{j}\n|position error| [mm]")
        axes[j, 0].set_title(f"parameters of {labels[j]}", fontsize=9, loc="left")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle("One-step prediction error of each phase's parameters over demonstration 0; dashed: true "
                 "boundaries (thesis fig. 16-19)")
    by_step = _save(fig, out / "prediction_error_by_step.png")

    # E_rho_i(theta_j) over the model's own (Viterbi) segmentation, as the thesis estimated it
    pe = prediction_errors(model, [(x["states"], x["forces"]) for x in demos])
    fig, ax = plt.subplots(figsize=(9, 4.8))
    width = 0.8 / K
    for j in range(K):
        ax.bar(np.arange(K) + j * width, pe.mse[:, j] * MM ** 2, width=width, color=colors[j],
               label=f"theta_{j}: {labels[j]}")
    ax.set_xticks(np.arange(K) + 0.4 - width / 2)
    ax.set_xticklabels([f"steps of {labels[i]}\n({pe.count[i]} steps)" for i in range(K)], fontsize=8)
    pose = model.n_state > 3
    ax.set_ylabel("mean squared one-step error\n" + ("[mm^2 + mrad^2]" if pose else "[mm^2]"))
    ax.set_yscale("log")
    ax.legend(fontsize=7, title="parameters")
    ax.set_title("E_rho_i(theta_j): each phase's steps predicted with each phase's parameters\n"
                 "(thesis fig. 20, 29)")
    return [by_step, _save(fig, out / "prediction_error_by_phase.png")]


def _runs(t: np.ndarray, v: np.ndarray, t_end: float) -> list[tuple[float, float, int]]:
    """(start, width, value) of each run of equal ``v`` over times ``t``; the last ends at t_end."""
    if len(v) == 0:
        return []
    cuts = [0, *_boundaries(v), len(v)]
    ends = [*t[cuts[1:-1]], t_end]
    return [(float(t[a]), float(e - t[a]), int(v[a])) for a, e in zip(cuts[:-1], ends)]


def reproduction_figure(path: Path, index: int, model, state: str, features: str, out: Path,
                        phase_to_truth=None, true_names=()) -> Path | str:
    """Reproduction ``index``: the force feature, the estimated phase beside the true phase
    it is scored against (the simulator's label of the same robot cycle, ``/robot/contact``
    ``true_phase``, as the report scores it), and alpha; ``phase_to_truth``: which true phase
    each learned phase is (the demonstrations' matching, as the report uses it)."""
    from matplotlib.patches import Patch

    plt = _plt()
    try:
        d = load_demonstration(path, state=state, features=features, allow_incomplete=True)
    except (OSError, ValueError) as exc:
        return f"reproduction {index}: {exc}"
    estimates, commanded, truth_by_seq = [], [], {}
    for m in read_episode(path).messages:
        if m.topic not in ("/estimator/phase", "/robot/command", "/robot/contact"):
            continue
        try:
            msg = loads(m.payload)
        except ValueError:
            continue
        try:
            if m.topic == "/estimator/phase":
                estimates.append((msg["stamp_ns"] / 1e9, msg["phase"], msg["posterior"], msg.get("seq")))
            elif m.topic == "/robot/contact":
                truth_by_seq.setdefault(msg["seq"], msg["true_phase"])
            else:
                commanded.append((msg["stamp_ns"] / 1e9, msg["phase"]))
        except (KeyError, TypeError):
            continue
    if not estimates:
        return f"reproduction {index}: no phase estimates recorded"
    estimates.sort(key=lambda e: e[0])
    K = model.n_phases
    mapping = {int(k): int(v) for k, v in (phase_to_truth or {}).items()}
    labels = phase_labels(K, mapping, true_names)
    t0 = d["t"][0]
    colors = _phase_colors(K)
    te = np.array([e[0] for e in estimates]) - t0
    est = np.array([e[1] for e in estimates], dtype=int)
    t_end = float(max(te[-1], d["t"][-1] - t0))
    # the true phase of each estimate's robot cycle: the pairs the report scores
    scored = [i for i, e in enumerate(estimates) if e[3] in truth_by_seq]
    true = np.array([truth_by_seq[estimates[i][3]] for i in scored], dtype=int)
    tt = te[scored]

    torque = d["forces"].shape[1] >= 6  # force_torque features: the torque panel too
    ratios = [3, 2.2, 1.6, 3] if torque else [3, 1.6, 3]
    fig, axes = plt.subplots(len(ratios), 1, figsize=(10, 2 * len(ratios) + 1.5), sharex=True,
                             gridspec_kw={"height_ratios": ratios})
    for a, name in enumerate("xyz"):
        axes[0].plot(d["t"] - t0, d["forces"][:, a], lw=1, label=f"F{name}")
        if torque:
            axes[1].plot(d["t"] - t0, d["forces"][:, 3 + a], lw=1, label=f"T{name}")
    axes[0].set_ylabel("force on tool [N]")
    if torque:
        axes[1].set_ylabel("torque on tool [N m]")
    for ax in axes[:2 if torque else 1]:
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)

    # phase strips: estimated (top), true (middle), where they disagree (bottom)
    ax = axes[-2]
    truth_colour = {v: colors[k] for k, v in mapping.items() if k < K}
    for start, width, k in _runs(te, est, t_end):
        ax.broken_barh([(start, width)], (2.1, 0.8), facecolors=[colors[k % len(colors)]])
    true_seen = sorted(set(true.tolist()))
    for start, width, v in _runs(tt, true, t_end):
        ax.broken_barh([(start, width)], (1.1, 0.8), facecolors=[truth_colour.get(v, UNMATCHED)],
                       hatch=None if v in truth_colour else "//", edgecolor="white" if v in truth_colour else "grey")
    accuracy = None
    if len(true) and mapping:
        accuracy = score_segmentation(true, est[scored], mapping=mapping).accuracy
        wrong = np.array([mapping.get(int(k), -1) for k in est[scored]]) != true
        for start, width, w in _runs(tt, wrong.astype(int), t_end):
            if w:
                ax.broken_barh([(start, width)], (0.35, 0.5), facecolors=["crimson"])
    ax.set_ylim(0.2, 3.0)
    ax.set_yticks([0.6, 1.5, 2.5])
    ax.set_yticklabels(["wrong", "true phase", "estimated phase"], fontsize=8)
    ax.grid(axis="x", alpha=0.3)
    present = sorted(set(est.tolist()) | {k for k, v in mapping.items() if v in true_seen})
    handles = [Patch(color=colors[k], label=labels[k]) for k in range(K) if k in present or k in mapping]
    handles += [Patch(facecolor=UNMATCHED, hatch="//", edgecolor="grey",
                      label=f"{_true_label(v, true_names)}: no learned phase") for v in true_seen
                if v not in truth_colour]
    if mapping:
        handles.append(Patch(color="crimson", label="estimate != true phase"))
    ax.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.005, 1.0), borderaxespad=0)

    post = np.array([e[2] for e in estimates])
    for k in range(post.shape[1]):
        axes[-1].plot(te, post[:, k], color=colors[k % len(colors)], lw=1.2,
                     label=labels[k] if k < len(labels) else f"phase {k}")
    axes[-1].set_ylabel("alpha [-]")
    axes[-1].set_ylim(-0.05, 1.05)
    axes[-1].set_xlabel("time [s]")
    axes[-1].legend(fontsize=7, loc="center left")
    axes[-1].grid(alpha=0.3)
    commanded.sort()
    tc = np.array([c[0] for c in commanded]) - t0
    pc = np.array([c[1] for c in commanded])
    for i in np.flatnonzero(np.diff(pc)) + 1:
        for a in axes:
            a.axvline(tc[i], color="red", ls=":", lw=0.9)
    how = (f"online phase accuracy {accuracy:.1%} over {len(true)} estimates" if accuracy is not None else
           "no learned-to-true phase mapping: not scored" if len(true) else "no true phase recorded")
    fig.suptitle(f"Reproduction {index}: force feature, estimated against true phase, alpha ({how})\n"
                 "dotted red: the commanded phase switches (thesis fig. 25)")
    return _save(fig, out / f"reproduction_{index:02d}_force_phase_alpha.png")


def in_run(run_dir: Path, path) -> Path:
    """A path report.json names: relative to the run's folder unless absolute."""
    return Path(path) if Path(path).is_absolute() else run_dir / path


def read_run_report(run_dir: Path) -> dict:
    """A finished run's report.json; FiguresError naming the file if there is none."""
    try:
        report = read_report(run_dir)
    except RunFolderError as exc:
        raise FiguresError(str(exc)) from None
    if "learning" not in report:
        raise FiguresError(f"{Path(run_dir) / 'report.json'}: not a run report (no 'learning')")
    return report


def write_figures(run_dir, progress=None) -> tuple[list[Path], list[str]]:
    """Every figure the run has data for, into RUN_DIR/figures/: (files written, what was
    skipped and why)."""
    run_dir = Path(run_dir)
    report = read_run_report(run_dir)
    out = run_dir / FIGURES_DIR
    out.mkdir(exist_ok=True)
    say = progress or (lambda _m: None)
    written, skipped = [], []
    model_path = report["learning"].get("model")
    if not model_path:
        return written, ["no learned model in the run"]
    task = load_task(in_run(run_dir, model_path))
    model = task.model
    recordings = [in_run(run_dir, e["path"]) for e in [*report.get("demonstrations", []),
                                                        *(report.get("reproductions") or [])] if e.get("path")]
    world = world_of_run(run_dir, recordings[:1])
    names = true_phase_names(world)
    labels = phase_labels(model.n_phases, task.phase_to_truth, names)
    demos = []
    for d in report.get("demonstrations", []):
        p = in_run(run_dir, d["path"])
        try:
            demos.append(load_demonstration(p, state=task.state, features=task.features,
                                            state_resolution=task.state_resolution, allow_incomplete=True))
        except (OSError, ValueError) as exc:
            skipped.append(f"demonstration {p.name}: {exc}")
    if demos:
        say(f"figures: {len(demos)} demonstrations")
        written.append(demonstrations_figure(demos, out))
        written.append(forward_figure(model, demos, out, labels))
        written.append(path_figure(model, demos, out, labels, world=world, goal=task.goal))
        written += prediction_figures(model, demos, out, labels)
    else:
        skipped.append("no demonstrations: their figures are not drawn")
    bic = bic_figure(report["learning"].get("selection") or {}, out)
    (written if isinstance(bic, Path) else skipped).append(bic)
    repro = report.get("reproductions") or []
    if repro:
        p = in_run(run_dir, repro[0]["path"])
        # the mapping the report scored this reproduction with, else the model's
        mapping = (repro[0].get("phases") or {}).get("mapping") or task.phase_to_truth
        fig = reproduction_figure(p, 0, model, task.state, task.features, out, phase_to_truth=mapping,
                                  true_names=names)
        (written if isinstance(fig, Path) else skipped).append(fig)
    return written, skipped
