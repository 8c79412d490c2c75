"""Each role's node config for a scenario: what the scenario's cell says, and the flags a
run adds (fault injection, the recorder's visual rate)."""

from __future__ import annotations

from pathlib import Path

from services.nodes import (CommanderConfig, EstimatorConfig, FoxgloveBridgeConfig, FtSensorConfig, RecorderConfig,
                            RobotConfig, Ros2Config, TeacherConfig)
from services.run.wire import udp_wiring
from services.runtime.config import with_flags
from services.scenario import Scenario


def node_configs(scenario: Scenario, options, roles, recordings: Path, offload_recording: bool) -> dict:
    """role -> node config for every role of ``roles``.  ``options``: the run's
    (``services.run.options.RunOptions``); ``offload_recording``: the transport wants the
    MCAP writing in a helper process."""
    sc, cell = scenario, scenario.cell
    configs = {
        "robot": RobotConfig(world=sc.world, seed=sc.seed, plate_friction=cell.plate_friction,
                             physics_substeps=cell.physics_substeps, fri=cell.fri),
        "ft_sensor": FtSensorConfig(seed=sc.seed, noise_scale=cell.sensor_noise),
        "teacher": TeacherConfig(world=sc.world),
        "recorder": RecorderConfig(out_dir=str(recordings), writer_process=offload_recording),
        "phase_estimator": EstimatorConfig(),
        "impedance_commander": CommanderConfig(),
        "foxglove_bridge": FoxgloveBridgeConfig(world=sc.world, port=options.foxglove or 0),
        "ros2": Ros2Config(world=sc.world, domain=options.ros2 or 0),
    }
    serve = options.serve
    # the lab's protocols: etar-bench serve (a lab's remote) or --wire udp (the run's own nodes)
    wire = udp_wiring() if options.wire == "udp" else {}
    if serve:
        wire = {"robot": serve.robot_flags(), "ft_sensor": serve.sensor_flags()}
    given = {"robot": options.robot_args, "impedance_commander": options.commander_args,
             "ft_sensor": options.sensor_args, "recorder": options.recorder_args, "ros2": options.ros2_args}
    for role in ("robot", "impedance_commander", "ft_sensor", "recorder", "phase_estimator", "ros2"):
        flags = tuple(wire.get(role, ())) + tuple(given.get(role, ()))
        if flags:
            configs[role] = with_flags(configs[role], flags)
    return {role: configs[role] for role in roles}
