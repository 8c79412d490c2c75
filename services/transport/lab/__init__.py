"""The lab's wire at the edge of the nodes: what a service process hands its node when the
node's config asks to speak a lab protocol (``edges``).  The nodes decide; these carry:
the robot's KRC over FRI/UDP (``robot_krc``, ``krc_udp``), the commander's FRI remote
socket (``fri_remote``), the sensor's Net F/T box (``robot_sim.wire.netft``), the
estimator's Net F/T client (``netft_client``) and the cell's ROS 2 node on rmw_zenoh's
wire (``ros2_wire``)."""

from __future__ import annotations


def edges(role: str, config, clock, session=None) -> dict:
    """The keyword arguments that give ``role``'s node its lab links for ``config``: each a
    factory the node calls with what the link hands back to it.  ``session``: the service's
    Zenoh session (None in one process), which ROS 2's wire shares.  The links' modules are
    imported where one is asked for: robot_sim.wire brings the FRI packets' compiled kernels
    (numba, a second of a process's start), which a service without a lab link never uses."""
    if role == "robot" and config.wire == "udp":
        from services.transport.lab.robot_krc import RobotKrcOverUdp

        return {"fri_udp": lambda cell: RobotKrcOverUdp(cell, config, clock)}
    if role == "impedance_commander" and config.fri_listen:
        from robot_sim.wire.fri_udp import host_port
        from services.transport.lab.fri_remote import FriRemoteSocket

        return {"fri_remote": lambda on_measurement: FriRemoteSocket(
            host_port(config.fri_listen, "fri_listen", listen=True), on_measurement, clock.now_ns)}
    if role == "phase_estimator" and config.netft:
        from robot_sim.wire.fri_udp import host_port
        from services.transport.lab.netft_client import NetFtStream

        return {"netft_stream": lambda on_wrench: NetFtStream(host_port(config.netft, "netft"),
                                                              config.netft_http_port, on_wrench, clock.now_ns)}
    if role == "ros2" and session is not None:
        from services.transport.lab.ros2_wire import RosNodeOverZenoh

        return {"ros2_link": lambda domain: RosNodeOverZenoh(session, domain)}
    if role == "ft_sensor" and config.netft:
        return {"netft_box": lambda ati_config, on_bias, tap: served_box(config, ati_config, on_bias, tap)}
    return {}


def served_box(config, ati_config, on_bias, tap):
    """The sensor's Net F/T box, served on ``config.netft`` (OSError naming the flags if a
    port is taken)."""
    from robot_sim.wire.netft import NetFtBox

    box = NetFtBox(ati_config, address=config.netft, rdt_port=config.netft_rdt_port,
                   http_port=config.netft_http_port, calibration_port=config.netft_calibration_port,
                   on_bias=on_bias, tap=tap)
    try:
        box.serve()
    except OSError as exc:
        raise OSError(f"--netft {config.netft}: cannot serve the Net F/T box (RDT UDP {config.netft_rdt_port}, "
                      f"HTTP {config.netft_http_port}, TCP {config.netft_calibration_port}): "
                      f"{exc.strerror or exc}; another box on that address? give another (127.0.0.2, ...) "
                      f"or other ports") from None
    return box
