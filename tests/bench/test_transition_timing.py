"""bench/transition_timing.py on a hand-made run whose delays are known: each true change of
phase, the first estimate that reaches it (through the report's phase mapping), how often the
estimate leaves it again within a second, and one line for a folder that is no run."""

from __future__ import annotations

import json
import runpy
from pathlib import Path

from services.recordings.writer import EpisodeWriter
from services.runtime.messages import ESTIMATOR_PHASE, ROBOT_CONTACT

ROOT = Path(__file__).resolve().parents[2]
TIMING = runpy.run_path(str(ROOT / "bench" / "transition_timing.py"))
RUN = "handmade"
SCENARIO = "name: handmade\nworld: valley\nclock: lockstep\nseed: 0\nstages:\n  - demonstrate: {count: 1}\n"
# true phases: free for 1000 cycles, the plate for 2000, the groove for 1000
TRUE = [0] * 1000 + [1] * 2000 + [2] * 1000
# the model's own labels: 2 is free motion, 0 the plate, 1 the groove (the report maps them)
MAPPING = {"0": 1, "1": 2, "2": 0}


def _estimate(cycle: int) -> int:
    """The model's phase at a robot cycle: the plate 30 ms late, the groove 700 ms late,
    and back on the plate once for 20 ms, 200 ms after the groove was named."""
    if cycle < 1030:
        return 2
    if cycle < 3700 or 3900 <= cycle < 3920:
        return 0
    return 1


def write_run(folder: Path) -> Path:
    (folder / "recordings").mkdir(parents=True)
    path = folder / "recordings" / "reproduction_00.mcap"
    with EpisodeWriter(path, run_id=RUN, episode_kind="reproduction", episode_index=0,
                       scenario_text=SCENARIO) as w:
        for seq, phase in enumerate(TRUE):
            t = 1_000_000_000 + seq * 1_000_000
            head = dict(seq=seq, stamp_ns=seq * 1_000_000, sent_ns=5_000_000_000 + seq)
            w.add(f"etar/{RUN}/robot/contact", ROBOT_CONTACT.encode(
                **head, wrench=[0.0] * 6, contact_force=[0.0] * 3, touching=[], true_phase=phase, episode=0), t)
            if seq % 10 == 0:  # the estimator's 100 Hz
                posterior = [0.0, 0.0, 0.0]
                posterior[_estimate(seq)] = 1.0
                w.add(f"etar/{RUN}/estimator/phase", ESTIMATOR_PHASE.encode(
                    **head, posterior=posterior, phase=_estimate(seq), input_seq=seq, ft_seq=seq, episode=0), t + 1)
    report = {"reproductions": [{"index": 0, "path": "recordings/reproduction_00.mcap",
                                 "phases": {"mapping": MAPPING}}]}
    (folder / "report.json").write_text(json.dumps(report))
    return folder


def test_each_transition_is_timed_by_the_first_estimate_that_reaches_it(tmp_path):
    rows = TIMING["transitions"](write_run(tmp_path / "run"))
    by = {(r["from"], r["to"]): r for r in rows}
    assert set(by) == {(0, 1), (1, 2)}, rows
    assert abs(by[(0, 1)]["delay_s"] - 0.030) < 1e-9 and by[(0, 1)]["left_again"] == 0
    assert abs(by[(1, 2)]["delay_s"] - 0.700) < 1e-9 and by[(1, 2)]["left_again"] == 1


def test_the_table_and_one_line_for_a_folder_that_is_no_run(tmp_path, capsys):
    run = write_run(tmp_path / "run")
    assert TIMING["main"]([str(run), str(run)]) == 0
    out = capsys.readouterr().out.splitlines()
    plate, groove = (next(line for line in out if line.startswith(p)) for p in ("0 -> 1", "1 -> 2"))
    assert plate.split()[3:5] == ["2", "+0.030"] and groove.split()[3:5] == ["2", "+0.700"], out
    assert groove.split()[-1] == "2", groove  # left again once in each of the two runs
    assert TIMING["main"]([str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path) in err[0] and "report.json" in err[0], err
