"""How the tool tip meets a surface, candidate by candidate: the numbers the contact was chosen by.

    python bench/contact_candidates.py                  # every candidate, the table (~2 min)
    python bench/contact_candidates.py --only shipped,dd8d265

Each candidate is a change to the shipped worlds' MuJoCo contact (robot_sim.world.tasks:
the cone, impratio, the friction rows' solreffriction, the normal's solref and solimp,
noslip, the physics step, the coupler's torsional friction).  For each, scripted episodes on the bare cell (no
services: the cell, the simulated teacher holding the tool, 1 ms FRI cycles) measure:

  valley plate / groove  a demonstration from the smoke scenario's start (seeds 0-3; seed 3's
                         teacher presses with the least force, 4 N):
                         airborne share and lift-offs per second while the tip slides on
                         a plate, then along the groove; the step-to-step jitter of
                         |contact force| (std of 1 ms differences); the sliding friction
                         ratio |F_t| / F_n against the plates' mu (0.25), its median and
                         the share of sliding steps within 10 % of mu ("at mu")
  coupler                a hose-coupler demonstration (seeds 0, 1): the tip pressed on the
                         socket's floor while the hand turns it a quarter turn; Tz the
                         median torque it costs, at the sensor
  creep mm/s             the tip resting on a plate pressed with 8 N, pushed along it with
                         1 N (half of mu N): how fast it slides where it should stick
  sink mm                how deep the same tip has sunk into the plate at rest, before the
                         push (MuJoCo's contact distance)
  vs 0.1 ms              the same valley demonstration (seed 0) with ten physics steps per
                         FRI cycle: RMS difference of |contact force| averaged over 10 ms
                         (the estimator's samples), relative to the fine one's, in contact
  floor us               bench/sim_step.py's physical floor (MuJoCo's step + the KRC's law,
                         the arm pressed on a plate) with this contact, per 1 ms FRI cycle

Airborne, lift/s, jitter and "at mu" are the worst seed's; mu and Tz the seeds' mean.

The test of the shipped contact (tests/robot_sim/test_contact.py) runs the same episodes.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from robot_sim.cell import RobotCell
from robot_sim.world.labels import CouplerLabeler, ValleyLabeler
from robot_sim.world.teacher import DOWN, HoseCouplerTeacher, ValleyTeacher
from robot_sim.world.tasks import (FRICTION_DAMPING, HoseCoupler, IMPRATIO, NORMAL_SOLIMP, NORMAL_SOLREF,
                                   Valley, WorldSpec, hose_coupler, physics_step, valley as valley_world)

VALLEY_START = (0.62, -0.06, 0.30)  # low over the left plate, the groove 4 s later (the stored smoke model's start)
VALLEY_GOAL_X = 0.57
COUPLER_START = HoseCoupler.start_left
SEAL_TORSION = HoseCoupler().torsional_friction


@dataclass
class Episode:
    force: np.ndarray  # (T, 3) contact force on the tip, world axes
    touching: list  # (T,) geom names
    phase: np.ndarray  # (T,) true phase
    velocity: np.ndarray  # (T, 3) tcp velocity, world axes
    position: np.ndarray  # (T, 3)
    torque: np.ndarray  # (T, 3) the torque the tool transmits to the F/T sensor, sensor axes


def scripted_demonstration(world: WorldSpec, seed: int = 0, max_seconds: float = 15.0) -> Episode:
    """A demonstration on the bare cell as the nodes run it: gravity compensation, the
    simulated teacher's hand on the tool's true motion, its wrench applied every cycle."""
    cell = RobotCell(world, seed=seed)
    coupler = world.name == "hose_coupler"
    start = np.array(COUPLER_START if coupler else VALLEY_START)
    cell.place_tcp(start, DOWN)
    cell.krc.gravity_compensation = True
    cell.start()
    rng = np.random.default_rng(seed)
    teacher = HoseCouplerTeacher(HoseCoupler(), start, rng) if coupler else \
        ValleyTeacher(world.task, start, VALLEY_GOAL_X, rng)
    labeler = CouplerLabeler() if coupler else ValleyLabeler()
    force, touching, phase, velocity, position, torque = [], [], [], [], [], []
    dt = cell.cycle_ns / 1e9
    for _ in range(int(max_seconds / dt)):
        cell.begin_cycle()
        pose, twist = cell.true_tcp_pose.reshape(3, 4), cell.true_tcp_twist
        touch = cell.touching
        force.append(cell.contact_force)
        touching.append(touch)
        phase.append(labeler.update(touch))
        velocity.append(twist[:3])
        position.append(pose[:, 3])
        torque.append(cell.tool_wrench[3:])
        hand = teacher.step(dt, pose[:, 3], twist[:3], pose[:, :3], twist[3:], cell.contact_force, touch)
        cell.end_cycle(hand)
        if (coupler and teacher.phase == 1 and teacher.rotation_done(pose[:, :3])) or teacher.done:
            break
    return Episode(np.array(force), touching, np.array(phase), np.array(velocity), np.array(position),
                   np.array(torque))


def contact_figures(e: Episode, phase: int, normal: np.ndarray | None = None, settle_s: float = 0.0,
                    mu: float = Valley.friction) -> dict:
    """Airborne share, lift-offs per second, |F| jitter (std of 1 ms differences, after
    ``settle_s`` of the phase: the landing's transient left out), and with a surface
    ``normal`` the sliding friction ratio (median) and the share of sliding steps whose
    ratio is within 10 % of ``mu``, over the steps of one true phase."""
    where = np.flatnonzero(e.phase == phase)
    if len(where) < 10:
        return {}
    touch = np.array([bool(e.touching[i]) for i in where])
    magnitude = np.linalg.norm(e.force[where], axis=1)
    steady = magnitude[int(settle_s * 1000):]
    out = {"seconds": len(where) / 1000, "airborne": float((~touch).mean()),
           "lift_per_s": float((touch[:-1] & ~touch[1:]).sum()) / (len(where) / 1000),
           "jitter_n": float(np.std(np.diff(steady))) if len(steady) > 2 else math.nan,
           "torque_nm": float(np.median(np.abs(e.torque[where, 2])))}
    if normal is not None:
        f = e.force[where]
        fn = f @ normal
        v = e.velocity[where]
        vt = np.linalg.norm(v - np.outer(v @ normal, normal), axis=1)
        sliding = (vt > 0.005) & (fn > 1.0) & touch
        ft = np.linalg.norm(f - np.outer(fn, normal), axis=1)
        ratio = ft[sliding] / fn[sliding]
        out["mu_ratio"] = float(np.median(ratio)) if sliding.any() else math.nan
        out["at_mu"] = float(np.mean(np.abs(ratio - mu) <= 0.1 * mu)) if sliding.any() else math.nan
    return out


def rest_on_plate(world: WorldSpec, push_n: float = 1.0, press_n: float = 8.0) -> tuple[float, float]:
    """(creep m/s, sink m) of the tip resting on a plate, pressed with ``press_n`` (the arm in
    gravity compensation, the hand keeping the tool upright): how deep it sinks after 1 s
    at rest (MuJoCo's contact distance), then its speed along the plate over 0.2 s once
    pushed along it with ``push_n`` at the flange, after 0.1 s to settle."""
    import pinocchio as pin

    g = world.task
    cell = RobotCell(world, seed=0, joint_noise=0.0)
    n = g.plate_normal(-1)
    downhill = np.array([0.0, math.cos(g.angle), -math.sin(g.angle)])
    y = -0.10
    cell.place_tcp(np.array([0.6, y, g.surface_z(y)]) + n * (cell.kin.description.tool.tip_radius - 5e-6), DOWN)
    cell.krc.gravity_compensation = True
    cell.start()
    hand = np.zeros(6)
    along, sink = [], math.nan
    for k in range(1300):
        if k == 1000:
            contacts = cell.sim.data.contact[:cell.sim.data.ncon]
            sink = -min((c.dist for c in contacts), default=math.nan)
        cell.begin_cycle()
        hand[:3] = -press_n * n + (push_n if k >= 1000 else 0.0) * downhill
        hand[3:] = 20.0 * pin.log3(DOWN @ cell.sim.tcp_rotation().T)
        cell.end_cycle(hand)
        along.append(cell.sim.tcp_position() @ downhill)
    return (along[-1] - along[-201]) / 0.2, sink


def estimator_rms(a: Episode, b: Episode) -> float:
    """RMS difference of |F| averaged over 10 ms, over the samples both spend in contact,
    relative to b's RMS."""
    def view(e):
        n = len(e.phase) // 10 * 10
        return (np.linalg.norm(e.force[:n], axis=1).reshape(-1, 10).mean(axis=1),
                (e.phase[:n] > 0).reshape(-1, 10).all(axis=1))
    (x, cx), (y, cy) = view(a), view(b)
    n = min(len(x), len(y))
    both = cx[:n] & cy[:n]
    return float(np.sqrt(np.mean((x[:n][both] - y[:n][both]) ** 2)) / np.sqrt(np.mean(y[:n][both] ** 2)))


# ---------------------------------------------------------------- candidates


def _edit(impratio=None, friction_damping=None, solref=None, solimp=None, cone=None, noslip=None, torsional=None,
          frictionless=False) -> Callable[[str], str]:
    """An edit of a shipped world's XML (robot_sim.world.tasks' header and pairs)."""
    def edit(xml: str) -> str:
        if impratio is not None:
            xml = xml.replace(f'impratio="{IMPRATIO!r}"', f'impratio="{impratio!r}"')
        if friction_damping is not None:
            # "0 0": the friction rows damped as the normal (MuJoCo's default)
            value = "0 0" if friction_damping == "normal" else f"0 {-friction_damping!r}"
            xml = xml.replace(f'solreffriction="0 {-FRICTION_DAMPING!r}"', f'solreffriction="{value}"')
        if solref is not None:
            xml = xml.replace(f'<pair condim="4" solref="{_f(NORMAL_SOLREF)}"', f'<pair condim="4" solref="{solref}"')
        if solimp is not None:
            xml = xml.replace(f'solimp="{_f(NORMAL_SOLIMP)}"', f'solimp="{solimp}"')
        if cone is not None:
            xml = xml.replace('cone="elliptic"', f'cone="{cone}"')
        if noslip is not None:
            xml = xml.replace('cone=', f'noslip_iterations="{noslip}" cone=')
        if torsional is not None:
            xml = xml.replace(f'friction="0.8 0.8 {SEAL_TORSION!r} ', f'friction="0.8 0.8 {torsional!r} ')
        if frictionless:
            xml = xml.replace('friction="0.25 0.25 0.005 ', 'friction="0.0 0.0 0.0 ').replace(
                f'friction="0.8 0.8 {SEAL_TORSION!r} ', 'friction="0.0 0.0 0.0 ')
        return xml
    return edit


# the contact up to dd8d265 (2026-12-04): the tip's automatic contacts, friction rows damped
# as the normal, impratio 0.01 (the same as an explicit pair with solreffriction "0 0"), the
# normal's impedance from 0.9 over 2 mm, the coupler's torsional friction 0.1 m
BEFORE = dict(impratio=0.01, friction_damping="normal", torsional=0.1, solimp="0.9 0.95 0.002")
OLD_NORMAL = "0.9 0.95 0.002"
CANDIDATES: dict[str, tuple[dict, int, str]] = {
    # name: (edit, physics substeps, what it is)
    "dd8d265": (BEFORE, 1, "the contact before: impratio 0.01, friction rows damped as the normal (105 /s), "
                           "impedance from 0.9 over 2 mm, coupler torsion 0.1 m"),
    "dd8d265-0.1ms": (BEFORE, 10, "the same at ten 0.1 ms physics steps per FRI cycle"),
    "frictionless": (dict(BEFORE, frictionless=True), 1, "no friction at all: what the normal contact alone does"),
    "pyramidal": (dict(BEFORE, cone="pyramidal"), 1, "dd8d265 with a pyramidal friction cone"),
    "noslip": (dict(BEFORE, noslip=10), 1, "dd8d265 with 10 noslip iterations (friction re-solved hard)"),
    "impratio-10": (dict(BEFORE, impratio=10.0), 1, "dd8d265 with impratio 10 (MuJoCo's 'preventing slip')"),
    "solref-4ms": (dict(BEFORE, solref="0.004 1"), 1, "dd8d265 with a stiffer normal contact, 4 ms"),
    "bf2-d0.9": (dict(friction_damping=2.0, solimp=OLD_NORMAL), 1,
                 "friction rows damped at 2 /s, impratio 10, impedance from 0.9 over 2 mm"),
    "bf2-d0.8": (dict(friction_damping=2.0, solimp="0.8 0.95 0.002"), 1, "the same, impedance from 0.8"),
    "bf2-d0.8-imp1": (dict(friction_damping=2.0, solimp="0.8 0.95 0.002", impratio=1.0), 1,
                      "the same, impratio 1"),
    "bf25-d0.8": (dict(friction_damping=25.0, solimp="0.8 0.95 0.002"), 1,
                  "friction rows damped at 25 /s, impratio 10, impedance from 0.8 over 2 mm"),
    "bf25-d0.5-2mm": (dict(friction_damping=25.0, solimp="0.5 0.95 0.002"), 1,
                      "the same, impedance from 0.5 over 2 mm"),
    "shipped": ({}, 1, f"as shipped: friction rows damped at {FRICTION_DAMPING:g} /s, impratio {IMPRATIO:g}, "
                       f"impedance from {NORMAL_SOLIMP[0]:g} over {NORMAL_SOLIMP[2] * 1e3:g} mm"),
    "shipped-0.1ms": ({}, 10, "the shipped contact at ten 0.1 ms physics steps per FRI cycle"),
    "shipped-t0.1": (dict(torsional=0.1), 1, "the shipped contact with the coupler's torsional friction 0.1 m"),
    "shipped-noslip": (dict(noslip=3), 1, "the shipped contact with 3 noslip iterations"),
}


def worlds_of(edit: dict, substeps: int) -> tuple[WorldSpec, WorldSpec]:
    step = physics_step(substeps)
    f = _edit(**edit)
    v, c = valley_world(timestep=step), hose_coupler(timestep=step)
    return (WorldSpec(v.name, f(v.xml), v.task, v.surfaces), WorldSpec(c.name, f(c.xml), c.task, c.surfaces))


def floor_us(valley: WorldSpec, cycles: int = 5000) -> float:
    sys.path.insert(0, str(Path(__file__).parent))
    try:
        import sim_step
    finally:
        sys.path.pop(0)
    return sim_step.physical_floor_us(cycles, valley)


def evaluate(name: str, seeds=(0, 1, 2, 3), coupler_seeds=(0, 1)) -> dict:
    edit, substeps, _ = CANDIDATES[name]
    valley, coupler = worlds_of(edit, substeps)
    normal = Valley().plate_normal(-1)
    out: dict = {"name": name}
    plate, groove, turn = [], [], []
    for seed in seeds:
        e = scripted_demonstration(valley, seed)
        plate.append(contact_figures(e, 1, normal))
        groove.append(contact_figures(e, 2, settle_s=0.1))
        if seed in coupler_seeds:
            turn.append(contact_figures(scripted_demonstration(coupler, seed), 1, settle_s=0.1))
        if seed == seeds[0]:
            fine = scripted_demonstration(worlds_of(edit, 10)[0], seed) if substeps != 10 else e
            out["vs_fine"] = estimator_rms(e, fine)
    for key, rows in (("plate", plate), ("groove", groove), ("coupler", turn)):
        for figure in ("airborne", "lift_per_s", "jitter_n", "mu_ratio", "at_mu", "torque_nm"):
            values = [r[figure] for r in rows if figure in r]
            if values:  # the worst seed's airborne share, lift-offs, jitter and share at mu; the mean ratio, torque
                worst = np.min(values) if figure == "at_mu" else np.max(values)
                out[f"{key}_{figure}"] = float(np.mean(values) if figure in ("mu_ratio", "torque_nm") else worst)
    out["creep_mps"], out["sink_m"] = rest_on_plate(valley)
    out["floor_us"] = floor_us(valley)
    return out


def _f(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def table(rows: list[dict]) -> str:
    head = (f"{'candidate':<15}{'plate air':>10}{'lift/s':>7}{'jit N':>7}{'mu':>6}{'at mu':>6} {'groove air':>10}"
            f"{'lift/s':>7}{'jit N':>7} {'coupler air':>11}{'lift/s':>7}{'jit N':>7}{'Tz Nm':>6} {'creep mm/s':>10} {'sink mm':>7} {'vs 0.1ms':>8} "
            f"{'floor us':>8}")
    lines = [head]
    for r in rows:
        lines.append(f"{r['name']:<15}{100 * r['plate_airborne']:>9.2f}%{r['plate_lift_per_s']:>7.1f}"
                     f"{r['plate_jitter_n']:>7.2f}{r['plate_mu_ratio']:>6.3f}{100 * r['plate_at_mu']:>5.0f}% "
                     f"{100 * r['groove_airborne']:>9.2f}%"
                     f"{r['groove_lift_per_s']:>7.1f}{r['groove_jitter_n']:>7.2f} {100 * r['coupler_airborne']:>10.2f}%"
                     f"{r['coupler_lift_per_s']:>7.1f}{r['coupler_jitter_n']:>7.2f}{r['coupler_torque_nm']:>6.2f} "
                     f"{1e3 * r['creep_mps']:>10.2f} {1e3 * r['sink_m']:>7.2f} "
                     f"{100 * r['vs_fine']:>7.1f}% {r['floor_us']:>8.1f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", type=lambda s: s.split(","), help=f"a comma list of {', '.join(CANDIDATES)}")
    args = ap.parse_args(argv)
    names = args.only or list(CANDIDATES)
    bad = [n for n in names if n not in CANDIDATES]
    if bad:
        ap.error(f"--only: unknown candidate(s) {', '.join(bad)} (known: {', '.join(CANDIDATES)})")
    rows = []
    for name in names:
        t0 = time.monotonic()
        rows.append(evaluate(name))
        print(f"{name}: {CANDIDATES[name][2]} ({time.monotonic() - t0:.0f} s)", file=sys.stderr, flush=True)
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
