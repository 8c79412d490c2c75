"""What the figures show, read from the matplotlib artists they draw: the 3-D tool path on
the task's surfaces with start and end markers and equal axes, the reproduction's estimated
beside its true phase, phases named by the true phase they were matched to, a unit on
every axis.  Fast: the stored smoke model and small synthetic demonstrations and
recordings, no run."""

from __future__ import annotations

import re

import numpy as np
import pytest
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from etar.task import load_task
from robot_sim.world.tasks import HoseCoupler, Valley
from services.recordings.writer import EpisodeWriter
from services.results.decoding import EpisodeReading, LearnerView, decode_episode
from services.results.figures import canvas, demonstrations, learning, phases, reproduction, tool_paths
from services.runtime.messages import (
    ESTIMATOR_PHASE,
    FT_WRENCH,
    ROBOT_COMMAND,
    ROBOT_CONTACT,
    ROBOT_STATE,
)
from tests import support

VALLEY_NAMES = ("free motion", "sliding along a plate", "sliding along the groove")
UNIT = re.compile(r"\[[^\]]+\]")


@pytest.fixture(scope="module")
def task():
    return load_task(support.SMOKE_MODEL)  # 3 phases, phase_to_truth {0: 0, 1: 1, 2: 2}


@pytest.fixture
def drawn(monkeypatch):
    """Every figure the module saves, kept for inspection (still written and closed)."""
    kept = []
    save = canvas.save

    def keep(fig, path, *args, **kwargs):
        kept.append(fig)
        return save(fig, path, *args, **kwargs)

    monkeypatch.setattr(canvas, "save", keep)
    return kept


def valley_demo(seed: int, T: int = 120) -> dict:
    """A synthetic valley demonstration (m, N, s): down onto the left plate, down it into
    the groove, along the groove towards -x; true phases 0, 1, 2 by segment."""
    rng = np.random.default_rng(seed)
    g = Valley()
    a, b = T // 4, T // 2
    y = np.concatenate([np.full(a, -0.06), np.linspace(-0.06, 0.0, b - a), np.zeros(T - b)])
    z = np.concatenate([np.linspace(0.30, g.surface_z(0.06), a), [g.surface_z(abs(v)) for v in y[a:]]])
    x = np.concatenate([np.full(b, 0.62), np.linspace(0.62, 0.57, T - b)])
    states = np.column_stack([x, y, z]) + rng.normal(scale=1e-4, size=(T, 3))
    truth = np.concatenate([np.zeros(a), np.ones(b - a), np.full(T - b, 2)]).astype(int)
    forces = np.where(truth[:, None] > 0, [0.0, 3.0, 6.0], 0.0) + rng.normal(scale=0.2, size=(T, 3))
    return {"states": states, "forces": forces, "phases": truth[1:], "t": np.arange(T) * 0.01, "dt": 0.01}


def labels_of(ax) -> list[str]:
    legend = ax.get_legend()
    return [t.get_text() for t in legend.get_texts()] if legend else []


def figure_legend_texts(fig) -> list[str]:
    texts = [t.get_text() for lg in fig.legends for t in lg.get_texts()]
    return texts + [t for ax in fig.axes for t in labels_of(ax)]


def marker_collection(ax, label):
    found = [c for c in ax.collections if c.get_label() == label]
    assert len(found) == 1, [c.get_label() for c in ax.collections]
    return found[0]


# ------------------------------------------------------------------ names of the phases


def test_a_phase_is_named_by_the_true_phase_it_was_matched_to_else_by_its_number():
    assert phases.phase_labels(3, {0: 0, 1: 1, 2: 2}, VALLEY_NAMES) == [
        "phase 0 = free motion", "phase 1 = sliding along a plate", "phase 2 = sliding along the groove"]
    # a permutation, string keys (model.json), an unmatched phase, a true phase the world does not name
    assert phases.phase_labels(4, {"0": 2, "2": 0, "3": 7}, VALLEY_NAMES) == [
        "phase 0 = sliding along the groove", "phase 1", "phase 2 = free motion", "phase 3"]
    assert phases.phase_labels(2, None, VALLEY_NAMES) == ["phase 0", "phase 1"]
    assert phases.phase_labels(2, {0: 0, 1: 1}, ()) == ["phase 0", "phase 1"]
    assert phases.true_phase_names("hose_coupler") == ("approach", "coupling")
    assert phases.true_phase_names("free_space") == () and phases.true_phase_names(None) == ()


def test_the_world_comes_from_the_runs_scenario(tmp_path):
    assert phases.world_of_scenario("name: x\nworld: hose_coupler\nstages: []\n") == "hose_coupler"
    assert phases.world_of_scenario("name: x\n") is None and phases.world_of_scenario(": [") is None
    (tmp_path / "scenario.yaml").write_text("name: x\nworld: valley\n")
    assert phases.world_of_run(tmp_path) == "valley"
    assert phases.world_of_run(tmp_path / "nowhere") is None


# ------------------------------------------------------------------ the 3-D tool path


def test_the_tool_path_lies_on_the_valleys_plates_with_start_end_goal_and_equal_axes(task, drawn, tmp_path):
    demos = [valley_demo(0), valley_demo(1)]
    labels = phases.phase_labels(3, task.phase_to_truth, VALLEY_NAMES)
    tool_paths.path_figure(task.model, demos, tmp_path, labels, world="valley", goal=task.goal)
    (fig,) = drawn
    ax = next(a for a in fig.axes if a.name == "3d")

    surfaces = [c for c in ax.collections if isinstance(c, Poly3DCollection)]
    assert len(surfaces) == 1 and len(surfaces[0].get_paths()) == 2  # the two plates
    starts, ends = marker_collection(ax, "start"), marker_collection(ax, "end")
    np.testing.assert_allclose(np.column_stack(starts._offsets3d), [d["states"][0] * 1e3 for d in demos])
    np.testing.assert_allclose(np.column_stack(ends._offsets3d), [d["states"][-1] * 1e3 for d in demos])
    goal = marker_collection(ax, "goal (learned: mean end)")
    np.testing.assert_allclose(np.column_stack(goal._offsets3d)[0], task.goal * 1e3)

    # the paths in mm, within the axes' limits
    pts = np.vstack([d["states"] for d in demos]) * 1e3
    limits = np.array([ax.get_xlim3d(), ax.get_ylim3d(), ax.get_zlim3d()])
    assert np.all(pts >= limits[:, 0]) and np.all(pts <= limits[:, 1])
    # equal axes: the box's sides in proportion to the ranges they show
    spans = limits[:, 1] - limits[:, 0]
    np.testing.assert_allclose(np.asarray(ax.get_box_aspect()) / ax.get_box_aspect()[0], spans / spans[0],
                               rtol=1e-6)
    # seen from near the groove's axis (x), from above: the V of the plates shows
    assert min(abs(ax.azim), abs(abs(ax.azim) - 180)) <= 40 and 20 <= ax.elev <= 40
    assert [ax.get_xlabel(), ax.get_ylabel(), ax.get_zlabel()] == ["x [mm]", "y [mm]", "z [mm]"]
    legend = figure_legend_texts(fig)
    assert {"phase 0 = free motion", "phase 1 = sliding along a plate", "phase 2 = sliding along the groove",
            "start", "end", "valley plates"} <= set(legend), legend


def test_the_coupler_path_shows_the_socket_and_a_world_without_a_task_no_surfaces(task, drawn, tmp_path):
    plt = canvas.pyplot()  # headless (Agg)
    c = np.array(HoseCoupler().center)
    path = np.linspace([0.62, -0.08, 0.36], c + [0, 0, 0.01], 50)
    fig = plt.figure()
    ax = fig.add_subplot(projection="3d")
    tool_paths.draw_paths_3d(ax, [path], [np.r_[np.zeros(40), np.ones(10)].astype(int)], canvas.phase_colours(2),
                          ["phase 0 = approach", "phase 1 = coupling"], world="hose_coupler")
    fig.canvas.draw()
    (socket,) = [col for col in ax.collections if isinstance(col, Poly3DCollection)]
    assert len(socket.get_paths()) > 10 and socket.get_label() == "coupler socket"
    assert ax.get_zlim3d()[0] <= c[2] * 1e3  # the socket's floor is in view
    plt.close(fig)
    # the socket where the world has it: floor at the centre's height, the bore's wall up to its depth
    corners = np.vstack(tool_paths.task_surfaces("hose_coupler", None, None, 0.0))
    radius = np.hypot(corners[:, 0] - c[0], corners[:, 1] - c[1])
    assert np.isclose(corners[:, 2].min(), c[2]) and np.isclose(corners[:, 2].max(), c[2] + HoseCoupler().depth)
    assert np.isclose(radius.min(), HoseCoupler().bore_radius)

    tool_paths.path_figure(task.model, [valley_demo(2)], tmp_path, world=None)
    ax = next(a for a in drawn[-1].axes if a.name == "3d")
    assert not [col for col in ax.collections if isinstance(col, Poly3DCollection)]
    assert {"phase 0", "phase 1", "phase 2", "start", "end"} <= set(figure_legend_texts(drawn[-1]))


# ------------------------------------------------------------------ the reproduction


def write_reproduction(path, n_cycles=400, lag=25, scenario="name: t\nworld: valley\n"):
    """A reproduction recording: true phase 0, 1, 2 over thirds of the cycles, the estimate
    the same ``lag`` cycles late, every 10th cycle; the commander follows the estimate."""
    truth = np.minimum(np.arange(n_cycles + 1) * 3 // n_cycles, 2)

    def pose(s):
        return np.concatenate([np.eye(3), [[0.62 - s * 1e-4], [-0.05], [0.25]]], axis=1).reshape(-1)

    with EpisodeWriter(path, run_id="figs", episode_kind="reproduction", episode_index=0,
                       scenario_text=scenario) as w:
        for seq in range(1, n_cycles + 1):
            head = {"seq": seq, "stamp_ns": seq * 1_000_000, "sent_ns": 10**9 + seq * 1000}
            t = 10**9 + seq * 1000
            est = int(truth[max(0, seq - lag)])
            w.add("etar/figs/robot/state", ROBOT_STATE.encode(
                **head, reflected_seq=seq - 1, fri_state=2, fri_quality=3, control_mode=2, msr_jnt_pos=[0.0] * 7,
                msr_cart_pos=pose(seq), est_ext_tcp_ft=[0.0] * 6, answer_rate=1.0, latency_s=2e-4, jitter_s=1e-5,
                miss_rate=0.0, safety=0, gravity_compensation=False, episode=0), t)
            force = [0.0, 2.0 * truth[seq], 5.0 * truth[seq], 0.0, 0.0, 0.0]
            w.add("etar/figs/ft/wrench", FT_WRENCH.encode(
                **head, rdt_sequence=seq, ft_sequence=seq, status=0, counts=[int(f * 1e6) for f in force],
                counts_per_force=1e6, counts_per_torque=1e6, wrench=force), t + 10)
            w.add("etar/figs/robot/contact", ROBOT_CONTACT.encode(
                **head, wrench=force, contact_force=[0.0] * 3, touching=[], true_phase=int(truth[seq]), episode=0),
                t + 20)
            w.add("etar/figs/robot/command", ROBOT_COMMAND.encode(
                **head, cart_pos=pose(seq), cart_stiffness=[1000.0] * 3 + [100.0] * 3, cart_damping=[0.7] * 6,
                add_tcp_ft=[0.0] * 6, requested_mode=2, phase=est, estimate_seq=seq, goal_reached=False, hold="",
                episode=0), t + 30)
            if seq % 10 == 0:
                post = np.full(3, 0.05)
                post[est] = 0.9
                w.add("etar/figs/estimator/phase", ESTIMATOR_PHASE.encode(
                    **head, posterior=post, phase=est, input_seq=seq, ft_seq=seq, episode=0), t + 40)
    seqs = np.arange(10, n_cycles + 1, 10)
    return truth[seqs], truth[np.maximum(0, seqs - lag)]


def trace_of(path):
    """A reproduction's trace as the figures decode it, in the learner's position/force view."""
    reading = EpisodeReading(str(path), measures=False, trace=LearnerView("position", "force"))
    return decode_episode(reading).figure_data.trace


def strip_axes(fig):
    (ax,) = [a for a in fig.axes if "true phase" in [t.get_text() for t in a.get_yticklabels()]]
    return ax


def strip_colours(ax, y_lo, y_hi):
    """(start, end, colour) of the bars whose band lies within y_lo..y_hi, in time order."""
    bars = []
    for col in ax.collections:
        for p, face in zip(col.get_paths(), np.resize(col.get_facecolors(), (len(col.get_paths()), 4))):
            v = p.vertices
            if y_lo <= v[:, 1].min() and v[:, 1].max() <= y_hi:
                bars.append((v[:, 0].min(), v[:, 0].max(), tuple(np.round(face[:3], 3))))
    return sorted(bars)


def test_the_reproduction_shows_the_estimated_beside_the_true_phase_it_is_scored_against(task, drawn, tmp_path):
    path = tmp_path / "reproduction_00.mcap"
    true, est = write_reproduction(path)
    mapping = {0: 0, 1: 1, 2: 2}
    out = reproduction.reproduction_figure(trace_of(path), 0, task.model, tmp_path, phase_to_truth=mapping,
                                      true_names=VALLEY_NAMES)
    assert out == tmp_path / "reproduction_00_force_phase_alpha.png" and out.is_file()
    (fig,) = drawn
    ax = strip_axes(fig)
    ticks = [t.get_text() for t in ax.get_yticklabels()]
    assert "estimated phase" in ticks and "true phase" in ticks
    colours = canvas.phase_colours(3)
    estimated = strip_colours(ax, 2.0, 3.0)
    truth = strip_colours(ax, 1.0, 2.0)
    assert [c for _, _, c in estimated] == [tuple(np.round(colours[k][:3], 3)) for k in (0, 1, 2)]
    assert [c for _, _, c in truth] == [tuple(np.round(colours[k][:3], 3)) for k in (0, 1, 2)]
    # the true phase changes first: the estimate is `lag` cycles late
    assert truth[1][0] < estimated[1][0] and truth[2][0] < estimated[2][0]
    wrong = strip_colours(ax, 0.3, 0.9)
    assert len(wrong) == 2  # the two late switches, nothing else
    # the accuracy the report would give: the same pairs (robot cycle), the same mapping
    assert f"online phase accuracy {np.mean(true == est):.1%} over {len(true)} estimates" in fig._suptitle.get_text()
    legend = figure_legend_texts(fig)
    assert {"phase 0 = free motion", "phase 1 = sliding along a plate", "phase 2 = sliding along the groove"} <= \
        set(legend), legend


def test_without_a_mapping_the_reproduction_names_phases_by_number_and_is_not_scored(task, drawn, tmp_path):
    path = tmp_path / "reproduction_00.mcap"
    write_reproduction(path, n_cycles=200)
    reproduction.reproduction_figure(trace_of(path), 0, task.model, tmp_path)
    (fig,) = drawn
    legend = figure_legend_texts(fig)
    assert "phase 0" in legend and not any("=" in t for t in legend), legend
    assert "not scored" in fig._suptitle.get_text()
    ax = strip_axes(fig)
    assert strip_colours(ax, 1.0, 2.0) and not strip_colours(ax, 0.3, 0.9)  # a true strip, no "wrong" one


# ------------------------------------------------------------------ units and names on every figure


def test_every_axis_label_carries_a_unit_and_every_phase_legend_names_the_true_phase(task, drawn, tmp_path):
    demos = [valley_demo(0), valley_demo(1)]
    labels = phases.phase_labels(3, task.phase_to_truth, VALLEY_NAMES)
    demonstrations.demonstrations_figure(demos, tmp_path)
    learning.forward_figure(task.model, demos, tmp_path, labels)
    tool_paths.path_figure(task.model, demos, tmp_path, labels, world="valley", goal=task.goal)
    learning.prediction_figures(task.model, demos, tmp_path, labels)
    learning.bic_figure({"criterion": "bic", "best": 3, "scores": {"2": 10.0, "3": 5.0, "4": 7.0}}, tmp_path)
    path = tmp_path / "reproduction_00.mcap"
    write_reproduction(path, n_cycles=200)
    reproduction.reproduction_figure(trace_of(path), 0, task.model, tmp_path, phase_to_truth={0: 0, 1: 1, 2: 2},
                                true_names=VALLEY_NAMES)
    assert len(drawn) == 7
    missing = []
    for fig in drawn:
        for ax in fig.axes:
            names = [ax.get_xlabel(), ax.get_ylabel()] + ([ax.get_zlabel()] if ax.name == "3d" else [])
            missing += [(fig._suptitle and fig._suptitle.get_text()[:40], n) for n in names if n and not UNIT.search(n)]
    assert not missing, missing
    # positions in mm where the axis says mm: the demonstrations' x in mm
    demo_fig = drawn[0]
    x_ax = demo_fig.axes[0]
    assert x_ax.get_ylabel() == "x [mm]"
    np.testing.assert_allclose(x_ax.get_lines()[0].get_ydata(), demos[0]["states"][:, 0] * 1e3)
    # every figure that names phases names them by their true phase
    for fig in drawn[1:5] + drawn[6:]:  # all but the demonstrations' and the BIC's
        legend = " | ".join(figure_legend_texts(fig) + [ax.get_title(loc="left") for ax in fig.axes]
                            + [t.get_text() for ax in fig.axes for t in ax.get_xticklabels()])
        assert "phase 1 = sliding along a plate" in legend, legend
