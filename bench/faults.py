"""Faults in one process, lockstep (exact and repeatable): what the arm does when its inputs fail.

    python bench/faults.py [--fault-at 1.5]

A reproduction with the stored smoke model (scenarios/models/smoke.json) from the start
its demonstrations had, [0.62, -0.06, 0.30], with each fault injected ``--fault-at``
seconds into it:

- the F/T sensor's stream stops, saturates or reads NaN (ft_sensor --fault):
  the hold's reason, the cycles from the fault to the hold, how far the tcp
  moved and how hard it pressed in the second of hold before the robot ends
  the episode;
- the FRI link loses every command packet for 60 ms (cell.fri_packet_loss 1
  within fri_faults_from_s/until_s): the cycles missed, command mode left and
  entered again;
- 30 % of the command packets arrive twice, 5 % held back past the next
  cycle's: what the KRC counted, and whether the arm's path changed.

The Zenoh cases (a service killed, a host cut off, a foreign peer) are tests
with their figures printed: pytest -s tests/e2e/test_supervision.py
tests/e2e/test_hosts.py tests/e2e/test_credentials.py.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

MODEL = str(ROOT / "scenarios" / "models" / "smoke.json")
START = [0.62, -0.06, 0.30]


def cell(sensor=None, **faults):
    """The reproduction's nodes in one process; ``faults``: the FRI link's (robot_sim.krc.faults.LinkFaultSpec)."""
    from robot_sim.krc.faults import LinkFaultSpec
    from services.nodes import CommanderConfig, EstimatorConfig, FtSensorConfig, RecorderConfig, RobotConfig
    from services.transport.inproc import InProcessCell

    return InProcessCell("faults", {
        "robot": RobotConfig(fri=LinkFaultSpec(**faults)), "ft_sensor": FtSensorConfig(**(sensor or {})),
        "recorder": RecorderConfig(out_dir=tempfile.mkdtemp()), "phase_estimator": EstimatorConfig(),
        "impedance_commander": CommanderConfig()})


def reproduce(c, seconds):
    """The smoke reproduction for ``seconds``, unrecorded (the episode protocol of every run)."""
    from services.run.episode import Episodes

    summary, _, _ = Episodes(c).reproduce(0, START, model=MODEL, stop_at_goal=False, max_seconds=seconds)
    return summary


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fault-at", type=float, default=1.5, help="seconds into the reproduction (default 1.5)")
    args = parser.parse_args()
    at = args.fault_at
    if not 0.1 <= at <= 4.0:
        parser.error(f"--fault-at must be within 0.1..4 s, got {at}")

    clean = reproduce(cell(), at + 2.0)
    print(f"smoke reproduction, lockstep, in one process; faults {at:g} s in; the clean run's peak contact force "
          f"{clean['peak_contact_force']:.1f} N")
    print(f"{'sensor fault':<14} {'hold reason':<18} {'cycles to hold':>14} {'tcp moved [mm]':>15} "
          f"{'peak force held [N]':>20}")
    for fault in ("stop", "saturate", "nan"):
        s = reproduce(cell(sensor=dict(fault=fault, fault_after=at)), at + 2.0)
        h = s.get("hold")
        if h is None:
            print(f"{fault:<14} NO HOLD ({s['reason']})")
            continue
        print(f"{fault:<14} {h['reason']:<18} {round((h['at_s'] - at) * 1000):14d} "
              f"{1e3 * h['max_displacement_m']:15.2f} {h['peak_contact_force']:20.1f}")

    dropout = reproduce(cell(packet_loss=1.0, faults_from_s=at, faults_until_s=at + 0.06), at + 2.0)
    f = dropout["fri"]
    print(f"FRI dropout of 60 ms: {f['missed']} cycles missed (longest run {f['longest_miss_run']}), command mode "
          f"left {f['command_mode_left']}x and entered {f['command_mode_entered']}x, ending in "
          f"{'CMD' if f['state'] == 2 else 'MON'}; peak contact force {dropout['peak_contact_force']:.1f} N")
    doubled = reproduce(cell(duplication=0.3), at + 2.0)
    same = doubled["final_position"] == clean["final_position"] and \
        doubled["peak_contact_force"] == clean["peak_contact_force"]
    print(f"30 % duplicated command packets: {doubled['fri']['duplicate']} rejected as duplicates, "
          f"{doubled['fri']['late']} copies late; the arm's path {'identical to' if same else 'DIFFERENT from'} "
          f"the clean run's")
    reordered = reproduce(cell(reordering=0.05), at + 2.0)
    r = reordered["fri"]
    print(f"5 % reordered command packets: {r['late']} late, {r['missed']} cycles missed, command mode "
          f"{'entered' if r['command_mode_entered'] else 'never entered (PERFECT needs a window without a miss)'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
