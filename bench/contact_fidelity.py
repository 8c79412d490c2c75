"""Contact fidelity of recorded runs: would a lab see these contact signals?

    python bench/contact_fidelity.py out/valley                         # a run's folder
    python bench/contact_fidelity.py out/valley out/coupler --json fidelity.json
    python bench/contact_fidelity.py out/valley --reference out/valley-fine --plot contact.png
    python bench/contact_fidelity.py sweeps/valley/runs/* --pool      # a sweep's runs as one

Reads recordings only (a run's ``recordings/*.mcap``, or the files themselves), so it
judges any run, old or new: the physics' own truth on ``/robot/contact`` (the contact
force on the tool tip, what it touches, the true phase), the ATI's reading on
``/ft/wrench``, the tool's motion (``tcp_twist`` where the recording has it: the slip of
the tip's point on the surface; else the tcp's, the measured pose on ``/robot/state``
differenced over 20 ms).  The world and the pair's
friction come from the scenario each recording carries.

Per task, episode kind and true phase (the contact phases: true phase > 0):

  airborne %     steps in which the tip touches nothing
  lift/s         contact -> no contact changes per second of the phase
  jitter N       std of the 1 ms differences of |contact force|
  ATI N          the sensor's own noise: std of the 1 ms differences of its force reading
                 in free motion (true phase 0) of the same episodes, RMS over x, y, z
  >20 Hz, >100 Hz  the share of |contact force|'s variance above 20 and 100 Hz (the
                 teacher's 10 Hz tremor lies below)
  mu ratio       median |F_t| / F_n while sliding (> 5 mm/s) on one surface with F_n > 1 N,
                 and the pair's mu
  stick-slip/s   per second: the tangential speed falling below 1 mm/s after it was above
                 5 mm/s, on one surface
  cmd N          reproductions: std of the 1 ms differences of the force the commander asks
                 for (|addTcpFT|): what the controller itself puts into the contact

``--reference RUN``: the same episodes run on a finer physics step (``cell.physics_substeps``):
the shipped run's |contact force| and the reference's, each averaged over the estimator's
10 ms samples (100 Hz), compared over the steps both spend in the contact phases (RMS of the
difference over RMS of the reference), and the lift-offs of each.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.runtime.messages import FT_WRENCH, ROBOT_COMMAND, ROBOT_CONTACT, ROBOT_STATE

SLIDING_MPS = 0.005  # above: the tip slides
STUCK_MPS = 0.001  # below: it sticks
MIN_NORMAL_N = 1.0
TIP_RADIUS = 0.010  # m: robot_sim.arm.description's tool tip (the tcp is its centre)
ESTIMATOR_SAMPLE = 10  # 1 ms cycles per estimator sample (100 Hz)
DIFFERENCE_STEPS = 20  # the measured pose is differenced over this many cycles where no true velocity is recorded


class StudyError(ValueError):
    """A recording or folder the study cannot read (the message names it)."""


@dataclass
class Episode:
    """One recording's signals, one entry per robot cycle."""

    path: Path
    run: str  # the run's folder
    task: str  # the world
    kind: str  # demonstration | reproduction | ...
    index: int
    mu: dict  # surface geom -> sliding friction of its pair
    phase: np.ndarray  # (T,) true phase
    force: np.ndarray  # (T, 3) contact force on the tip, world axes
    touching: list  # (T,) lists of geom names
    velocity: np.ndarray  # (T, 3) tcp velocity, world axes
    angular: np.ndarray  # (T, 3) the tool's angular velocity, world axes (NaN where not recorded)
    velocity_source: str
    position: np.ndarray  # (T, 3) tcp position
    ati: np.ndarray | None  # (T, 3) the ATI's force reading, sensor axes (cycles without one: NaN)
    commanded: np.ndarray | None  # (T,) |addTcpFT force| the commander sent (reproductions; else None)
    normals: dict = field(default_factory=dict)  # geom -> (axis, centre) of the face the tip rests on


# ------------------------------------------------------------------ reading


def recordings_of(paths) -> list[Path]:
    out = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted((p / "recordings").glob("*.mcap")) or sorted(p.glob("*.mcap"))
            if not found:
                raise StudyError(f"{p}: no recordings (expected a run's folder with recordings/*.mcap)")
            out += found
        elif p.suffix == ".mcap" and p.is_file():
            out.append(p)
        else:
            raise StudyError(f"{p}: neither a run's folder nor an .mcap file")
    return out


def _surfaces(scenario: dict) -> tuple[str, dict, dict]:
    """(world, geom -> mu, geom -> normal function) of a recording's scenario, from the
    world as robot_sim.world.tasks builds it with the scenario's friction."""
    import mujoco

    from robot_sim.world.tasks import Valley, WORLDS, valley

    world = scenario.get("world", "valley")
    if world not in WORLDS:
        raise StudyError(f"world {world!r} is not one of {', '.join(WORLDS)}")
    spec = valley(Valley(friction=float(scenario.get("cell", {}).get("plate_friction", Valley.friction)))) \
        if world == "valley" else WORLDS[world]()
    model = mujoco.MjModel.from_xml_string(spec.xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    mu, normals = {}, {}
    for name in spec.contact_geoms:
        g = model.geom(name).id
        surface = getattr(spec, "surfaces", {}).get(name)
        mu[name] = surface.sliding if surface is not None else float(model.geom_friction[g][0])
        normals[name] = _face_normal(model.geom_type[g], data.geom_xpos[g].copy(),
                                     data.geom_xmat[g].reshape(3, 3).copy(), model.geom_size[g].copy())
    return world, mu, normals


def _face_normal(gtype, centre, rotation, size):
    """(axis, centre) of the face a tip rests on: a box's thinnest axis, a cylinder's axis
    (the tip on its top); the normal is the axis signed towards the tip."""
    import mujoco

    if gtype == mujoco.mjtGeom.mjGEOM_BOX:
        return rotation[:, int(np.argmin(size[:3]))], centre
    if gtype == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return rotation[:, 2], centre
    raise StudyError(f"a surface of geom type {int(gtype)}: only boxes and cylinders are understood")


def read(path: Path) -> Episode:
    import yaml

    from services.recordings.arrays import recording_arrays
    from services.recordings.format import RecordingError
    from services.recordings.reader import read_episode

    try:
        episode = read_episode(path)
        # a foreign peer's garbage is not the physics: left out
        arrays = recording_arrays(path, skip_bad=True, topics=tuple(m.channel for m in (
            ROBOT_CONTACT, ROBOT_STATE, FT_WRENCH, ROBOT_COMMAND)))
    except RecordingError as exc:
        raise StudyError(str(exc)) from None
    if ROBOT_CONTACT.channel not in arrays:
        raise StudyError(f"{path}: no /robot/contact in this recording: the physics' truth is what is judged")
    text = episode.attachments.get("scenario.yaml")
    scenario = yaml.safe_load(text) if text else {}
    world, mu, normals = _surfaces(scenario if isinstance(scenario, dict) else {})
    c = arrays[ROBOT_CONTACT.channel]
    seq = c["seq"]
    order = np.argsort(seq, kind="stable")
    seq = seq[order]
    keep = np.concatenate([[True], np.diff(seq) != 0])  # a replayed cycle counts once
    order, seq = order[keep], seq[keep]
    touching = [list(c["touching"][i]) for i in order]
    if "tcp_twist" in c and not np.isnan(c["tcp_twist"]).any():
        velocity, angular, source = c["tcp_twist"][order, :3], c["tcp_twist"][order, 3:], "true, at the contact point"
        position = c["tcp_pose"][order].reshape(-1, 3, 4)[:, :, 3]
    else:
        state = arrays.get(ROBOT_STATE.channel)
        if state is None:
            raise StudyError(f"{path}: neither a true tcp velocity nor /robot/state to difference")
        by_seq = dict(zip(state["seq"].tolist(), state["msr_cart_pos"].reshape(-1, 3, 4)[:, :, 3]))
        position = np.array([by_seq.get(int(s), (np.nan,) * 3) for s in seq])
        k = DIFFERENCE_STEPS
        velocity = np.full_like(position, np.nan)
        if len(position) > k:
            velocity[k // 2: len(position) - k + k // 2] = (position[k:] - position[:-k]) / (k * 1e-3)
        angular = np.full_like(position, np.nan)
        source = f"the tcp's, measured pose differenced over {k} ms"
    ati = None
    ft = arrays.get(FT_WRENCH.channel)
    if ft is not None:
        by_seq = dict(zip(ft["seq"].tolist(), ft["wrench"][:, :3]))
        ati = np.array([by_seq.get(int(s), (np.nan,) * 3) for s in seq])
    commanded = None
    command = arrays.get(ROBOT_COMMAND.channel)
    if command is not None and len(command["seq"]):
        by_seq = dict(zip(command["seq"].tolist(), np.linalg.norm(command["add_tcp_ft"][:, :3], axis=1)))
        commanded = np.array([by_seq.get(int(s), np.nan) for s in seq])
    meta = episode.metadata
    run = path.parent.parent if path.parent.name == "recordings" else path.parent
    return Episode(path, str(run), world, meta.get("episode_kind", "?"), int(meta.get("episode_index", -1)), mu,
                   c["true_phase"][order].astype(int), c["contact_force"][order], touching, velocity, angular, source,
                   position, ati, commanded, normals)


# ---------------------------------------------------------------- measuring


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of each run of True."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


def high_frequency_share(signal: np.ndarray, cutoff_hz: float, rate_hz: float = 1000.0) -> tuple[float, float]:
    """(variance above cutoff_hz, total variance) of one contiguous stretch, mean removed."""
    x = np.asarray(signal, float) - np.mean(signal)
    if len(x) < 4:
        return 0.0, 0.0
    power = np.abs(np.fft.rfft(x)) ** 2
    freq = np.fft.rfftfreq(len(x), 1.0 / rate_hz)
    return float(power[freq > cutoff_hz].sum()), float(power[1:].sum())


def ati_noise(episodes: list[Episode]) -> float:
    """RMS over x, y, z of the std of the ATI reading's 1 ms differences in free motion."""
    diffs = []
    for e in episodes:
        if e.ati is None:
            continue
        for a, b in _runs(e.phase == 0):
            x = e.ati[a:b]
            d = np.diff(x, axis=0)
            d = d[np.isfinite(d).all(axis=1)]
            if len(d):
                diffs.append(d)
    if not diffs:
        return math.nan
    d = np.concatenate(diffs)
    return float(np.sqrt(np.mean(np.var(d, axis=0))))


def _tangential(e: Episode, a: int, b: int):
    """Over steps [a, b): tangential speed, normal force, tangential force, and whether the
    tip touches exactly one surface whose face is known (the others' figures are NaN)."""
    n = b - a
    normals = np.full((n, 3), np.nan)
    for i, t in enumerate(e.touching[a:b]):
        if len(t) == 1 and t[0] in e.normals:
            axis, centre = e.normals[t[0]]
            normals[i] = axis
            if (e.position[a + i] - centre) @ axis < 0:
                normals[i] = -axis
    f, v = e.force[a:b], e.velocity[a:b]
    w = e.angular[a:b]
    if np.isfinite(w).all():
        # the tip's surface point on the contact slides, not its centre: the tool turns
        # under the hand while its tip rolls (v + w x (-r n))
        v = v + np.cross(w, -TIP_RADIUS * np.nan_to_num(normals))
    fn = np.einsum("ij,ij->i", f, normals)
    vn = np.einsum("ij,ij->i", v, normals)
    speed = np.linalg.norm(v - vn[:, None] * normals, axis=1)
    ft = np.linalg.norm(f - fn[:, None] * normals, axis=1)
    single = np.isfinite(speed)
    return speed, fn, ft, single


def _stick_events(speed: np.ndarray, single: np.ndarray) -> int:
    """The times the speed falls below STUCK_MPS after it was above SLIDING_MPS, on one
    surface all along (touching anything else, or lifting off, starts over)."""
    events, slid = 0, False
    for s, ok in zip(speed.tolist(), single.tolist()):
        if not ok:
            slid = False
        elif s > SLIDING_MPS:
            slid = True
        elif s < STUCK_MPS and slid:
            events += 1
            slid = False
    return events


def measure(episodes: list[Episode], phase: int) -> dict:
    """The figures of the module docstring for one true phase over a group of episodes."""
    steps = airborne = lifts = 0
    jumps, hf20, hf100, total, ratios, mus, commanded = [], 0.0, 0.0, 0.0, [], set(), []
    stick, single_s = 0, 0.0
    for e in episodes:
        for a, b in _runs(e.phase == phase):
            touch = np.array([bool(t) for t in e.touching[a:b]])
            steps += b - a
            airborne += int((~touch).sum())
            lifts += int((touch[:-1] & ~touch[1:]).sum())
            magnitude = np.linalg.norm(e.force[a:b], axis=1)
            jumps.append(np.diff(magnitude))
            if e.commanded is not None:
                d = np.diff(e.commanded[a:b])
                commanded.append(d[np.isfinite(d)])
            for cutoff, acc in ((20.0, "hf20"), (100.0, "hf100")):
                above, var = high_frequency_share(magnitude, cutoff)
                if acc == "hf20":
                    hf20 += above
                    total += var
                else:
                    hf100 += above
            speed, fn, ft, single = _tangential(e, a, b)
            single_s += 1e-3 * int(single.sum())
            sliding = single & (speed > SLIDING_MPS)
            pressed = sliding & (fn > MIN_NORMAL_N)
            ratios += (ft[pressed] / fn[pressed]).tolist()
            mus.update(e.mu[t[0]] for t, p in zip(e.touching[a:b], pressed) if p)
            stick += _stick_events(speed, single)
    if not steps:
        return {}
    jumps = np.concatenate(jumps) if jumps else np.zeros(0)
    seconds = steps * 1e-3
    return {"episodes": len(episodes), "seconds": seconds, "airborne": airborne / steps, "lift_per_s": lifts / seconds,
            "jitter_n": float(np.std(jumps)) if len(jumps) > 1 else math.nan,
            "above_20hz": hf20 / total if total else math.nan, "above_100hz": hf100 / total if total else math.nan,
            "mu_ratio": float(np.median(ratios)) if ratios else math.nan,
            "sliding_samples": len(ratios), "mu": sorted(mus),
            "stick_slip_per_s": stick / single_s if single_s else math.nan,
            "command_jitter_n": float(np.std(np.concatenate(commanded))) if commanded and
            sum(map(len, commanded)) > 1 else math.nan}


def study(episodes: list[Episode], pool: bool = False) -> list[dict]:
    """One row per (run, task, kind, contact phase), runs in the order given; ``pool``: the
    runs' episodes together, one row per (task, kind, contact phase)."""
    rows = []
    groups: dict[tuple, list[Episode]] = {}
    for e in episodes:
        groups.setdefault(("all runs" if pool else e.run, e.task, e.kind), []).append(e)
    for (run, task, kind), group in groups.items():
        noise = ati_noise(group)
        for phase in sorted({int(p) for e in group for p in np.unique(e.phase)} - {0}):
            m = measure(group, phase)
            if m:
                rows.append({"run": run, "task": task, "kind": kind, "phase": phase, "ati_noise_n": noise,
                             "jitter_over_ati": m["jitter_n"] / noise if noise > 0 else math.nan, **m})
    return rows


def estimator_view(episode: Episode) -> tuple[np.ndarray, np.ndarray]:
    """(|contact force| averaged over each 10 ms estimator sample, in contact phase or not)."""
    n = len(episode.phase) // ESTIMATOR_SAMPLE * ESTIMATOR_SAMPLE
    magnitude = np.linalg.norm(episode.force[:n], axis=1).reshape(-1, ESTIMATOR_SAMPLE).mean(axis=1)
    contact = (episode.phase[:n] > 0).reshape(-1, ESTIMATOR_SAMPLE).all(axis=1)
    return magnitude, contact


def against_reference(episodes: list[Episode], references: list[Episode]) -> list[dict]:
    """Each episode against the reference's of the same kind and index."""
    by_key = {(e.kind, e.index): e for e in references}
    rows = []
    for e in episodes:
        r = by_key.get((e.kind, e.index))
        if r is None:
            continue
        a, ca = estimator_view(e)
        b, cb = estimator_view(r)
        n = min(len(a), len(b))
        both = ca[:n] & cb[:n]
        if both.sum() < 10:
            continue
        diff = a[:n][both] - b[:n][both]
        lifts = []
        for x in (e, r):
            t = np.array([bool(v) for v in x.touching]) | (x.phase == 0)
            lifts.append(int((t[:-1] & ~t[1:]).sum()))
        rows.append({"kind": e.kind, "index": e.index, "samples": int(both.sum()),
                     "rms_difference_n": float(np.sqrt(np.mean(diff ** 2))),
                     "rms_reference_n": float(np.sqrt(np.mean(b[:n][both] ** 2))),
                     "relative": float(np.sqrt(np.mean(diff ** 2)) / max(np.sqrt(np.mean(b[:n][both] ** 2)), 1e-12)),
                     "lift_offs": lifts[0], "reference_lift_offs": lifts[1]})
    return rows


# ----------------------------------------------------------------- showing


def table(rows: list[dict]) -> str:
    runs = list(dict.fromkeys(r["run"] for r in rows))
    lines = []
    for run in runs:
        lines += [f"{run}:", _table([r for r in rows if r["run"] == run]), ""]
    return "\n".join(lines).rstrip()


def _table(rows: list[dict]) -> str:
    head = (f"{'task':<13}{'kind':<14}{'phase':>5} {'s':>6} {'airborne':>9} {'lift/s':>7} {'jitter N':>9} "
            f"{'ATI N':>6} {'x ATI':>6} {'>20 Hz':>7} {'>100 Hz':>8} {'mu ratio':>9} {'mu':>5} {'stick/s':>8} {'cmd N':>6}")
    lines = [head]
    for r in rows:
        mu = "/".join(f"{m:g}" for m in r["mu"]) or "-"
        lines.append(f"{r['task']:<13}{r['kind']:<14}{r['phase']:>5} {r['seconds']:>6.1f} {100 * r['airborne']:>8.2f}% "
                     f"{r['lift_per_s']:>7.2f} {r['jitter_n']:>9.3f} {r['ati_noise_n']:>6.3f} "
                     f"{r['jitter_over_ati']:>6.2f} {100 * r['above_20hz']:>6.1f}% {100 * r['above_100hz']:>7.1f}% "
                     f"{r['mu_ratio']:>9.3f} {mu:>5} {r['stick_slip_per_s']:>8.2f} {r['command_jitter_n']:>6.3f}")
    return "\n".join(lines)


def plot(episodes: list[Episode], references: list[Episode], path: Path, seconds: float = 0.4) -> None:
    """|contact force| and the ATI's |force| over ``seconds`` in the middle of the first
    episode's first contact phase, with the reference's where given."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e = next((x for x in episodes if (x.phase == 1).sum() > seconds * 1000), None)
    if e is None:
        raise StudyError(f"no episode has {seconds} s in its first contact phase to plot")
    where = np.flatnonzero(e.phase == 1)
    a = int(where[len(where) // 2 - int(seconds * 500)])
    sl = slice(a, a + int(seconds * 1000))
    t = np.arange(sl.stop - sl.start) * 1e-3
    fig, ax = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    ax[0].plot(t, np.linalg.norm(e.force[sl], axis=1), lw=0.8, label=f"{e.path.parent.parent.name}: contact |F|")
    r = next((x for x in references if (x.kind, x.index) == (e.kind, e.index)), None)
    if r is not None:
        ax[0].plot(t, np.linalg.norm(r.force[sl], axis=1), lw=0.8, label=f"reference ({r.path.parent.parent.name})")
    ax[0].set_ylabel("contact |F| [N]")
    ax[0].legend(loc="lower right")
    if e.ati is not None:
        ax[1].plot(t, np.linalg.norm(e.ati[sl], axis=1), lw=0.8, color="tab:green")
    ax[1].set_ylabel("ATI |F| [N]")
    ax[1].set_xlabel(f"s from {a / 1000:.2f} s of {e.kind} {e.index} (true phase 1)")
    fig.suptitle(f"{e.task}: the tip on the surface, 1 ms steps")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="runs' folders or .mcap recordings")
    ap.add_argument("--reference", nargs="+", default=[], metavar="RUN",
                    help="the same episodes on a finer physics step, to compare with")
    ap.add_argument("--pool", action="store_true", help="one table for all the runs' episodes (e.g. a sweep's seeds)")
    ap.add_argument("--json", type=Path, help="write the rows here too")
    ap.add_argument("--plot", type=Path, help="draw 0.4 s of the first contact phase (PNG)")
    args = ap.parse_args(argv)
    try:
        episodes = [read(p) for p in recordings_of(args.runs)]
        references = [read(p) for p in recordings_of(args.reference)] if args.reference else []
        rows = study(episodes, args.pool)
        print(table(rows))
        sources = sorted({e.velocity_source for e in episodes})
        print(f"tangential speed from: {', '.join(sources)}")
        compared = against_reference(episodes, references) if references else []
        if references:
            print(f"\nagainst the reference ({len(references)} recordings), |F| averaged over 10 ms samples in "
                  "the contact phases:")
            for c in compared:
                print(f"  {c['kind']} {c['index']:>2}: RMS difference {c['rms_difference_n']:.3f} N of "
                      f"{c['rms_reference_n']:.3f} N ({100 * c['relative']:.1f} %), lift-offs {c['lift_offs']} "
                      f"(reference {c['reference_lift_offs']}), {c['samples']} samples")
            if compared:
                worst = max(compared, key=lambda c: c["relative"])
                print(f"  worst: {worst['kind']} {worst['index']}, {100 * worst['relative']:.1f} %")
        if args.json:
            args.json.write_text(json.dumps({"rows": rows, "against_reference": compared}, indent=1) + "\n")
        if args.plot:
            plot(episodes, references, args.plot)
            print(f"plot: {args.plot}")
    except StudyError as exc:
        print(f"contact_fidelity: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
