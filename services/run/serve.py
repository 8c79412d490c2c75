"""``etar-bench serve``: the simulated cell alone, for a lab's own FRI remote and Net F/T client.

The world, the arm behind its KRC and the ATI sensor, on the realtime clock, with the
recorder: the robot speaks FRI 1.0 over UDP (``--wire udp``: measurement datagrams to
the remote's address every cycle, a KRL program on the KRL channels) and the sensor
serves a Net F/T box.  The arm is held where the scenario's first reproduction would
start (without its random perturbation), or at ``--start``, in monitor mode, until the
remote asks the KRL program for command mode.  One episode of kind ``served`` runs for
``max_seconds`` (or until Ctrl-C), recorded to ``recordings/served_00.mcap``; the
report says what the remote did.
"""

from __future__ import annotations

import dataclasses
import errno
import ipaddress
import math
import socket
from dataclasses import dataclass

from robot_sim.wire.fri_udp import host_port
from robot_sim.wire.fri_datagrams import REMOTE_PORT
from robot_sim.krc.krl import LAB_CONVENTIONS
from services.scenario import Scenario
from services.scenario.checks import MAX_EPISODE_SECONDS
from services.scenario.starts import reproduction_starts
from services.runtime.messages import FT_WRENCH, ROBOT_CONTACT, ROBOT_STATE

# what the recorder waits for before it closes the served episode's file
SERVED_TOPICS = (ROBOT_STATE.topic, ROBOT_CONTACT.topic, FT_WRENCH.topic)


@dataclass(frozen=True)
class ServeOptions:
    fri_remote: str = f"127.0.0.1:{REMOTE_PORT}"  # where the KRC sends its measurements
    fri_bind: str = "127.0.0.1:0"  # the KRC's own socket
    krl: str = "frilibrary"
    netft: str | None = "127.0.0.1"  # the Net F/T box's address (None: no box)
    netft_ports: tuple = ()  # extra ft_sensor flags for the box's ports
    start: tuple | None = None  # the tcp's start, m (None: the scenario's reproduction start)
    fri_cycle_ms: int = 1  # friOpen's cycle
    max_seconds: float = 60.0

    def __post_init__(self):
        host_port(self.fri_remote, "--fri-remote")
        host_port(self.fri_bind, "--fri-bind", listen=True)
        if self.krl not in LAB_CONVENTIONS:
            raise ValueError(f"--krl must be one of {', '.join(LAB_CONVENTIONS)}, got {self.krl!r}")
        if self.netft is not None:
            try:
                ipaddress.IPv4Address(self.netft)
            except ValueError:
                raise ValueError(f"--netft {self.netft}: not an IPv4 address (e.g. 127.0.0.1; 'none': no box)") from None
        if not (isinstance(self.max_seconds, (int, float)) and math.isfinite(self.max_seconds)
                and 0 < self.max_seconds <= MAX_EPISODE_SECONDS):
            # one served session is one episode, one recording: bounded as a scenario's episode is
            raise ValueError(f"--max-seconds must be a number of seconds > 0 and <= {MAX_EPISODE_SECONDS:g}, "
                             f"got {self.max_seconds!r}")
        self._check_ports()
        if isinstance(self.fri_cycle_ms, bool) or not isinstance(self.fri_cycle_ms, int) \
                or not 1 <= self.fri_cycle_ms <= 100:
            raise ValueError(f"--fri-cycle-ms must be an integer 1..100 (friOpen's range), got {self.fri_cycle_ms!r}")
        if self.start is not None and (len(self.start) != 3 or not all(math.isfinite(v) for v in self.start)):
            raise ValueError(f"--start must be three finite numbers X,Y,Z in m, got {self.start!r}")

    def _check_ports(self) -> None:
        flags = dict(zip(self.netft_ports[::2], self.netft_ports[1::2]))
        if flags and self.netft is None:
            raise ValueError(f"{' '.join(flags)}: the ports of a Net F/T box, but --netft none serves no box")
        for flag, value in flags.items():
            if not (value.isdigit() and 0 <= int(value) <= 65535):
                raise ValueError(f"{flag} {value}: not a port number 0..65535 (0: any free one)")
        # every socket the cell will bind, tried now: a port another serve (or anything) holds
        # is named before anything starts, not found by a service once the run is up
        host, port = host_port(self.fri_bind, "--fri-bind", listen=True)
        _free(socket.SOCK_DGRAM, host, port, f"--fri-bind {self.fri_bind}")
        if self.netft is not None:
            from robot_sim.wire.netft import CALIBRATION_PORT, HTTP_PORT, RDT_PORT

            for flag, kind, default in (("--netft-rdt-port", socket.SOCK_DGRAM, RDT_PORT),
                                        ("--netft-http-port", socket.SOCK_STREAM, HTTP_PORT),
                                        ("--netft-calibration-port", socket.SOCK_STREAM, CALIBRATION_PORT)):
                port = int(flags.get(flag, default))
                _free(kind, self.netft, port, f"the Net F/T box's {'UDP' if kind == socket.SOCK_DGRAM else 'TCP'} "
                                              f"port ({flag} {port})")

    def robot_flags(self) -> tuple:
        return ("--wire", "udp", "--fri-remote", self.fri_remote, "--fri-bind", self.fri_bind, "--krl", self.krl,
                "--fri-cycle-ms", str(self.fri_cycle_ms))

    def sensor_flags(self) -> tuple:
        return (("--netft", self.netft) + tuple(self.netft_ports)) if self.netft else ()


def _free(kind: int, host: str, port: int, what: str) -> None:
    """Refuse a port that is taken (port 0 is any free one)."""
    if port == 0:
        return
    with socket.socket(socket.AF_INET, kind) as s:
        if kind == socket.SOCK_STREAM:  # as the box's servers bind (a closed serve's TIME_WAIT is free)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            why = ("is taken (is another serve running?)" if exc.errno == errno.EADDRINUSE else
                   f"cannot be bound ({exc.strerror})")
            raise ValueError(f"{what}: {host}:{port} {why}; choose another port, or 0 for any free one") from None


def served_start(scenario: Scenario, options: ServeOptions) -> tuple[float, float, float]:
    """Where the arm is held: ``--start``, or the scenario's first reproduction start
    without its random perturbation."""
    if options.start is not None:
        return tuple(float(v) for v in options.start)
    stages = scenario.reproduce_stages
    if not stages:
        raise ValueError(f"{scenario.source}: the scenario has no reproduce stage to take the start from; "
                         f"give --start X,Y,Z")
    stage = stages[0]
    unperturbed = dataclasses.replace(stage, count=1, start_perturbation=0.0, min_distance_from_demonstrations=0.0)
    (_, start), = reproduction_starts(unperturbed, scenario.world, scenario.seed, [])
    return tuple(float(v) for v in start)
