"""The fused engine's cell (services.transport.fused) against the per-message one's, a
reproduction at a time: the same faults end the same way, with the same counters, and
the recorder takes the same messages (the clean case: tests/e2e/test_engines.py)."""

import json
import tempfile

import pytest

from robot_sim.krc.faults import LinkFaultSpec
from services.nodes import CommanderConfig, EstimatorConfig, FtSensorConfig, RecorderConfig, RobotConfig
from services.run.episode import Episodes
from services.recordings.format import WALL_CLOCK_TOPICS
from services.recordings.reader import read_episode
from services.transport.fused import FusedCell
from services.transport.inproc import InProcessCell
from tests import support

START = [0.62, -0.06, 0.30]
# what the wall clock decides in an episode's summary
WALL = ("wall_seconds", "sent_ns", "loop")


def reproduce(cell_class, *, robot=None, sensor=None, estimator=None, seconds=2.7) -> tuple[dict, dict, list]:
    """The smoke reproduction with the stored model in a cell of ``cell_class``: its summary
    without the wall clock's figures, every node's status, and the recorded messages
    (topic, payload without sent_ns; not the wall-clock topics)."""
    out = tempfile.mkdtemp()
    c = cell_class("engines", {
        "robot": robot or RobotConfig(), "ft_sensor": sensor or FtSensorConfig(),
        "recorder": RecorderConfig(out_dir=out, visual_rate_hz=0), "phase_estimator": estimator or EstimatorConfig(),
        "impedance_commander": CommanderConfig()})
    try:
        path = c.request("recorder", "begin_episode", path="reproduction.mcap", kind="reproduction")["path"]
        summary, _, _ = Episodes(c).reproduce(0, START, model=support.SMOKE_MODEL, stop_at_goal=False,
                                              max_seconds=seconds)
        c.request("recorder", "end_episode")
        status = {role: {k: v for k, v in c.request(role, "status").items() if k not in ("sections", "receive_to_answer")}
                  for role in ("robot", "ft_sensor", "phase_estimator", "impedance_commander")}
    finally:
        c.close()
    messages = [(m.topic, {k: v for k, v in json.loads(m.payload).items() if k != "sent_ns"})
                for m in read_episode(path).messages if m.topic not in WALL_CLOCK_TOPICS]
    return {k: v for k, v in summary.items() if k not in WALL}, status, messages


@pytest.mark.parametrize("case", [
    dict(robot=RobotConfig(fri=LinkFaultSpec(packet_loss=0.2, duplication=0.3, delay_ms=1.5))),
    dict(sensor=FtSensorConfig(fault="stop", fault_after=1.5)),
    dict(sensor=FtSensorConfig(fault="nan", fault_after=1.5)),
    dict(estimator=EstimatorConfig(mute_after=1.0)),
], ids=["fri-lost-duplicated-late", "sensor-stop", "sensor-nan", "estimator-mute"])
def test_the_fused_cell_ends_each_fault_as_the_per_message_cell_does(case):
    per_message = reproduce(InProcessCell, **case)
    fused = reproduce(FusedCell, **case)
    assert fused[0] == per_message[0]  # why and when it ended, the hold, the FRI link's counts
    assert fused[1] == per_message[1]  # every node's counters: faulted, skipped, muted, missing estimates
    assert len(fused[2]) == len(per_message[2]) > 1000
    assert sorted(fused[2], key=repr) == sorted(per_message[2], key=repr)


def test_a_command_asking_for_a_mode_fri_has_not_is_refused_and_the_episode_goes_on(monkeypatch):
    """Every 200th robot/command asks for requested_mode 7, no FRI control mode (what a
    foreign peer may publish): the KRC counts it as a corrupt packet and closes its cycle
    without it (bridged), the episode going on, alike in both engines (the robot node raised
    ValueError there before)."""
    from services.runtime.messages import ROBOT_COMMAND

    real = ROBOT_COMMAND.pack

    def odd_mode(**values):
        if values["seq"] % 200 == 0:
            values["requested_mode"] = 7
        return real(**values)

    monkeypatch.setattr(ROBOT_COMMAND, "pack", odd_mode)
    per_message = reproduce(InProcessCell, seconds=1.5)
    fused = reproduce(FusedCell, seconds=1.5)
    assert fused[0] == per_message[0] and fused[1] == per_message[1]
    assert sorted(fused[2], key=repr) == sorted(per_message[2], key=repr)
    assert fused[0]["fri"]["corrupt"] >= 5 and fused[0]["reason"] == "elapsed", fused[0]
