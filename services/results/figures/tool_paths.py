"""The tool paths in 3-D (thesis fig. 15b, 24b): the demonstrated paths coloured by the
estimated (Viterbi) phase on the task's surfaces (the valley's plates, the coupler's
socket), each path's start and end and the learned goal, equal axes, seen across the
motion."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np

from robot_sim.world.tasks import HoseCoupler, Valley
import services.results.figures.canvas as canvas
from services.results.figures.phases import phase_labels


def sample_phases(step_phases, n_samples: int) -> np.ndarray:
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
        surf = Poly3DCollection([np.asarray(p) * canvas.MM for p in polys], facecolor=(0.62, 0.66, 0.72, 0.35),
                                edgecolor=(0.35, 0.38, 0.42, 0.6), linewidth=0.4, zorder=0)
        surf.set_label({"valley": "valley plates", "hose_coupler": "coupler socket"}.get(world, "task surfaces"))
        ax.add_collection3d(surf)
        corners = np.vstack([np.asarray(p) for p in polys])
        lo, hi = np.minimum(lo, corners.min(axis=0)), np.maximum(hi, corners.max(axis=0))
    for p, ph in zip(paths, phases):
        p = np.asarray(p, dtype=float)[:, :3] * canvas.MM
        ph = np.asarray(ph, dtype=int)
        cuts = [0, *canvas.boundaries(ph), len(ph)]
        for a, b in itertools.pairwise(cuts):
            seg = p[max(0, a - 1):b]  # from the last sample of the previous run: the path stays joined
            ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color=colors[ph[a]], lw=2.0, zorder=2)
    for k, label in enumerate(labels):
        if label is not None:  # None: a phase left out of the legend
            ax.plot([], [], [], color=colors[k], lw=2.5, label=label)
    starts = np.array([np.asarray(p, dtype=float)[0, :3] for p in paths]) * canvas.MM
    ends = np.array([np.asarray(p, dtype=float)[-1, :3] for p in paths]) * canvas.MM
    ax.scatter(starts[:, 0], starts[:, 1], starts[:, 2], marker="o", s=45, color="black", depthshade=False,
               zorder=3, label="start")
    ax.scatter(ends[:, 0], ends[:, 1], ends[:, 2], marker="X", s=70, color="black", edgecolor="white",
               linewidth=0.6, depthshade=False, zorder=3, label="end")
    if goal is not None:
        g = np.asarray(goal, dtype=float)[:3] * canvas.MM
        # hollow: the paths' ends (crosses) lie at the goal, their mean
        ax.scatter([g[0]], [g[1]], [g[2]], marker="*", s=420, facecolor="none", edgecolor="darkgoldenrod",
                   linewidth=1.6, depthshade=False, zorder=4, label="goal (learned: mean end)")
    lo_mm, hi_mm = lo * canvas.MM, hi * canvas.MM
    ax.set_xlim(lo_mm[0], hi_mm[0])
    ax.set_ylim(lo_mm[1], hi_mm[1])
    ax.set_zlim(lo_mm[2], hi_mm[2])
    ax.set_box_aspect(tuple(np.maximum(hi_mm - lo_mm, 1e-3)))  # equal scale on the three axes
    ax.set_proj_type("ortho")
    ax.view_init(*view_angles(pts, world))
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")


def path_figure(model, demos, out: Path, labels=None, world=None, goal=None) -> Path:
    plt = canvas.pyplot()
    colors = canvas.phase_colours(model.n_phases)
    labels = labels or phase_labels(model.n_phases)
    fig = plt.figure(figsize=(10, 7))
    ax = fig.add_axes((0.0, 0.02, 0.72, 0.86), projection="3d")
    paths, phases = [], []
    for d in demos:
        paths.append(d["states"][:, :3])
        phases.append(sample_phases(model.viterbi(d["states"], d["forces"]), len(d["states"])))
    draw_paths_3d(ax, paths, phases, colors, labels, world=world, goal=goal)
    fig.legend(*ax.get_legend_handles_labels(), fontsize=8, loc="center left", bbox_to_anchor=(0.7, 0.5))
    where = {"valley": " in the valley", "hose_coupler": " at the hose coupler"}.get(world, "")
    fig.suptitle(f"Demonstrated tool paths{where}, coloured by the estimated (Viterbi) phase\n"
                 "circle: start, cross: end (thesis fig. 15b, 24b)")
    return canvas.save(fig, out / "tool_path_by_phase.png", laid_out=True)
