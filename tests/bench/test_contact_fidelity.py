"""bench/contact_fidelity.py on a hand-made recording whose figures are known in closed form:
airborne share, lift-offs, jitter, the ATI's noise, the share above 100 Hz, the friction
ratio, stick-slip events, the commander's jitter and the comparison with a reference; bad
input gets one line."""

from __future__ import annotations

import math
import runpy
from pathlib import Path

import numpy as np
import pytest

from robot_sim.world.tasks import Valley
from services.recordings.writer import EpisodeWriter
from services.runtime.messages import FT_WRENCH, ROBOT_COMMAND, ROBOT_CONTACT

ROOT = Path(__file__).resolve().parents[2]
STUDY = runpy.run_path(str(ROOT / "bench" / "contact_fidelity.py"))
RUN = "handmade"
SCENARIO = "name: handmade\nworld: valley\nclock: lockstep\nseed: 0\nstages:\n  - demonstrate: {count: 1}\n"
MU = Valley.friction
FREE, PLATE, GROOVE = 300, 1000, 500  # steps of each true phase
ATI_SIGMA = 0.05  # N, the hand-made sensor's white noise per axis
STUCK = (500, 800)  # the steps (of the plate phase) where the tip stops for 10 cycles
DROPS = (1500, 1700)  # single steps without contact in the groove


def _pose(p) -> list:
    return [-1.0, 0.0, 0.0, p[0], 0.0, 1.0, 0.0, p[1], 0.0, 0.0, -1.0, p[2]]


def write(path: Path, kind: str = "reproduction", scale: float = 1.0, index: int = 0) -> Path:
    """FREE steps in free motion (ATI noise only), PLATE steps sliding down the left plate at
    5 cm/s with F_n = 5 N +- 0.1 N alternating and |F_t| = mu F_n (stopped twice for 10
    steps), GROOVE steps pressed 8 N into the groove with two single-step drops to nothing."""
    g = Valley()
    n = g.plate_normal(-1)
    downhill = np.array([0.0, math.cos(g.angle), -math.sin(g.angle)])
    surface = np.array([0.6, -0.05, g.surface_z(0.05)]) + n * 0.01
    rng = np.random.default_rng(4)
    with EpisodeWriter(path, run_id=RUN, episode_kind=kind, episode_index=index, scenario_text=SCENARIO) as w:
        for seq in range(FREE + PLATE + GROOVE):
            head = dict(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=5_000_000_000 + seq)
            t = 1_000_000_000 + seq * 1_000_000
            velocity = np.zeros(3)
            if seq < FREE:
                phase, force, touching = 0, np.zeros(3), []
            elif seq < FREE + PLATE:
                k = seq - FREE
                fn = 5.0 + (0.1 if k % 2 else -0.1)
                phase, touching = 1, ["plate_left"]
                stopped = any(s <= k < s + 10 for s in STUCK)
                velocity = np.zeros(3) if stopped else 0.05 * downhill
                force = scale * (fn * n - MU * fn * downhill)
            else:
                phase = 2
                drop = seq in DROPS
                force, touching = (np.zeros(3), []) if drop else (scale * np.array([0.0, 0.0, 8.0]),
                                                                   ["plate_left", "plate_right"])
            pose = _pose(surface)
            w.add(f"etar/{RUN}/robot/contact", ROBOT_CONTACT.encode(
                **head, wrench=[0.0] * 6, contact_force=force.tolist(), touching=touching, true_phase=phase,
                tcp_pose=pose, tcp_twist=[*velocity.tolist(), 0.0, 0.0, 0.0], episode=index), t)
            ati = force + rng.normal(0.0, ATI_SIGMA, 3)
            w.add(f"etar/{RUN}/ft/wrench", FT_WRENCH.encode(
                **head, rdt_sequence=seq, ft_sequence=seq, status=0, counts=[0] * 6, counts_per_force=1e6,
                counts_per_torque=1e6, wrench=[*ati.tolist(), 0.0, 0.0, 0.0]), t + 1)
            if kind == "reproduction":
                # the commander's force: 1 N, then 2 N every other cycle of the plate phase
                push = 2.0 if (phase == 1 and seq % 2) else 1.0
                w.add(f"etar/{RUN}/robot/command", ROBOT_COMMAND.encode(
                    **head, cart_pos=pose, cart_stiffness=[0.0] * 6, cart_damping=[0.7] * 6,
                    add_tcp_ft=[0.0, 0.0, push, 0.0, 0.0, 0.0], requested_mode=2, phase=phase, estimate_seq=-1,
                    goal_reached=False, hold="", episode=index), t + 2)
    return path


@pytest.fixture
def recording(tmp_path):
    folder = tmp_path / "run" / "recordings"
    folder.mkdir(parents=True)
    return write(folder / "reproduction_00.mcap")


def test_the_study_measures_what_was_recorded(recording):
    rows = {r["phase"]: r for r in STUDY["study"]([STUDY["read"](recording)])}
    plate, groove = rows[1], rows[2]
    assert plate["task"] == "valley" and plate["kind"] == "reproduction"
    # plate: always touching, |F| = F_n sqrt(1 + mu^2) alternating by +-0.1 N: its 1 ms
    # differences are +-0.2 sqrt(1 + mu^2), all of its variance at 500 Hz
    assert plate["airborne"] == 0.0 and plate["lift_per_s"] == 0.0
    assert plate["jitter_n"] == pytest.approx(0.2 * math.sqrt(1 + MU ** 2), rel=1e-6)  # 999 differences: mean 1e-3
    assert plate["above_100hz"] == pytest.approx(1.0, abs=1e-9)
    assert plate["mu_ratio"] == pytest.approx(MU, rel=1e-9) and plate["mu"] == [MU]
    assert plate["sliding_samples"] == PLATE - 10 * len(STUCK)
    assert plate["stick_slip_per_s"] == pytest.approx(len(STUCK) / (PLATE / 1000), rel=1e-9)
    # the commander's push alternates 1 and 2 N in the plate phase: differences of +-1 N
    assert plate["command_jitter_n"] == pytest.approx(1.0, rel=1e-3)
    # groove: two single-step drops of 8 N in GROOVE steps: 2 lift-offs in 0.5 s, and four
    # differences of 8 N among GROOVE - 1
    assert groove["airborne"] == pytest.approx(len(DROPS) / GROOVE)
    assert groove["lift_per_s"] == pytest.approx(len(DROPS) / (GROOVE / 1000))
    d = np.zeros(GROOVE - 1)
    d[:2 * len(DROPS)] = 8.0 * np.array([1, -1] * len(DROPS))
    assert groove["jitter_n"] == pytest.approx(float(np.std(d)), rel=1e-9)
    assert math.isnan(groove["mu_ratio"])  # two surfaces at once: no one normal
    # the ATI's noise from the free phase: white noise of ATI_SIGMA differenced
    assert plate["ati_noise_n"] == pytest.approx(math.sqrt(2) * ATI_SIGMA, rel=0.1)


def test_the_reference_comparison_and_the_command(recording, tmp_path, capsys):
    ref_dir = tmp_path / "fine" / "recordings"
    ref_dir.mkdir(parents=True)
    same = write(ref_dir / "reproduction_00.mcap")
    assert STUDY["against_reference"]([STUDY["read"](recording)], [STUDY["read"](same)])[0]["relative"] == 0.0
    scaled = write(tmp_path / "scaled.mcap", scale=1.1)
    row = STUDY["against_reference"]([STUDY["read"](recording)], [STUDY["read"](scaled)])[0]
    # |F| 10 % larger throughout the contact phases (the two drops fall in samples left out)
    assert row["relative"] == pytest.approx(0.1 / 1.1, rel=1e-6)
    assert row["lift_offs"] == row["reference_lift_offs"] == len(DROPS)
    plot = tmp_path / "contact.png"
    assert STUDY["main"]([str(recording.parent.parent), "--reference", str(ref_dir.parent), "--plot", str(plot),
                          "--json", str(tmp_path / "rows.json")]) == 0
    out = capsys.readouterr().out
    assert "reproduction  0: RMS difference 0.000 N" in out and plot.stat().st_size > 10_000


def test_bad_input_is_one_line(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert STUDY["main"]([str(empty)]) == 2
    assert capsys.readouterr().err.strip() == f"contact_fidelity: {empty}: no recordings (expected a run's " \
                                              "folder with recordings/*.mcap)"
    not_mcap = tmp_path / "x.mcap"
    not_mcap.write_bytes(b"not an mcap file at all")
    assert STUDY["main"]([str(not_mcap)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"contact_fidelity: {not_mcap}") and "\n" not in err
    bare = tmp_path / "bare.mcap"
    with EpisodeWriter(bare, run_id=RUN, episode_kind="demonstration", episode_index=0) as w:
        w.add(f"etar/{RUN}/ft/wrench", b"{not json", 1)  # a foreign peer's garbage is left out, not fatal
    assert STUDY["main"]([str(bare)]) == 2
    assert capsys.readouterr().err.strip() == (f"contact_fidelity: {bare}: no /robot/contact in this recording: "
                                               "the physics' truth is what is judged")
