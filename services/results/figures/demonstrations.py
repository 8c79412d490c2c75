"""The demonstrations as recorded (thesis fig. 13, 21): each one's tool position and contact
force (and torque) over time; one demonstration beside its tool path, coloured by the
true phase (``etar-bench demo --png``)."""

from __future__ import annotations

from pathlib import Path

import services.results.figures.canvas as canvas
from services.results.figures.phases import true_phase_names, world_of_recording
from services.results.figures.tool_paths import draw_paths_3d, sample_phases


def demonstrations_figure(demos, out: Path) -> Path:
    plt = canvas.pyplot()
    torque = all(d["forces"].shape[1] >= 6 for d in demos)  # force_torque features: the turn shows in the torque
    rows = 3 if torque else 2
    fig, axes = plt.subplots(rows, 3, figsize=(12, 3 * rows), sharex=True)
    for i, d in enumerate(demos):
        t = d["t"] - d["t"][0]
        for a in range(3):
            axes[0, a].plot(t, d["states"][:, a] * canvas.MM, lw=1, label=f"demonstration {i}")
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
    return canvas.save(fig, out / "demonstrations_position_and_force.png")


def demonstration_figure(demo: dict, path: Path, title: str = "", phase_names=(), world=None) -> Path:
    """One demonstration (``load_demonstration``'s arrays): the 3-D tool path coloured by the
    true phase on the task's surfaces, beside the tool position and the (tared) force in
    base axes over time (thesis fig. 13 and 15b).  ``world``: the task world (default: the
    one in the recording's scenario, if ``demo`` names its recording)."""
    plt = canvas.pyplot()
    p, t = demo["states"][:, :3], demo["t"] - demo["t"][0]
    ph = sample_phases(demo["phases"], len(p))
    if world is None and demo.get("path"):
        world = world_of_recording(demo["path"])
    names = list(phase_names) or list(true_phase_names(world))
    n = max(int(ph.max()) + 1, len(names))
    labels = [names[k] if k < len(names) else f"true phase {k}" for k in range(n)]
    colours = canvas.phase_colours(n)
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
        axp.plot(t, p[:, i] * canvas.MM, label=c)
        axf.plot(t, demo["forces"][:, i], label=f"F{c}")
    for ax_ in (axp, axf):
        for b in canvas.boundaries(ph):
            ax_.axvline(t[b], color="k", lw=0.8, ls="--")
        ax_.legend(loc="upper right", fontsize=8)
        ax_.grid(alpha=0.3)
    axp.set_ylabel("tool position [mm]")
    axf.set_ylabel("force on tool [N]")
    axf.set_xlabel("time [s]  (dashed: true phase changes)")
    return canvas.save(fig, Path(path))
