"""How a scenario is run, as opposed to what it runs: the output folder, the transport and
where its processes go (a sweep's too: ``check_cluster``), what the machine is asked for.
Every rule about which options go together is here, checked on construction (``RunOptions``)
and against the scenario (``check``), for the command line and the API alike: a refusal is a
ValueError (or a ScenarioError, CredentialsError, HostsError naming what is at fault) before
anything starts.
"""

from __future__ import annotations

import math
import socket
from dataclasses import dataclass

from services.ros2.wire import check_domain
from services.run.realtime_profile import parse_profile
from services.runtime import topics
from services.runtime.roles import CELL_ROLES, FIFO_CHAIN
from services.scenario import Scenario, ScenarioError
from services.transport.carriers import TRANSPORTS, carrier, check_engine
from services.transport.session import ZenohOptions


WIRES = ("zenoh", "udp")


@dataclass(frozen=True)
class RunOptions:
    out: str
    run_id: str | None = None  # None: <scenario>-<random>
    # zenoh: every node in its own process (the lab's layout, realtime or lockstep);
    # inproc: every node in this process on an in-memory bus (lockstep only: speed, sweeps)
    transport: str = "zenoh"
    # inproc: how the FRI cycles are stepped, per-message or fused (services.transport.carriers.
    # ENGINES); None: the default
    engine: str | None = None
    zenoh: ZenohOptions | None = None  # None: the runner listens on a free loopback port
    robot_args: tuple = ()  # extra flags for the robot (e.g. fault injection)
    commander_args: tuple = ()
    sensor_args: tuple = ()  # extra flags for the ft_sensor (e.g. --fault saturate)
    recorder_args: tuple = ()  # extra flags for the recorder (e.g. --visual-rate-hz 0)
    # the run's credentials (etar-bench certs DIR): the runner is the run's router, mutual
    # TLS only, and only the run's roles may use its keys (services.transport.credentials)
    tls: str | None = None
    # the services on hosts in network namespaces (services.transport.hosts), roles by host:
    # 'robot,ft_sensor:phase_estimator,impedance_commander:recorder,teacher'
    hosts: str | None = None
    # the thesis' figures (RUN_DIR/figures/) and report.html after the report; a sweep's
    # runs leave them out (their table and plots are the sweep's)
    figures: bool = True
    # the visual topics live over Foxglove's WebSocket protocol on this port (services.nodes.
    # foxglove_bridge, one more service); None: no live view (recordings have them regardless)
    foxglove: int | None = None
    # the cell on ROS 2's rmw_zenoh wire in this domain (services.nodes.ros2, one more service);
    # None: not on ROS 2's wire (etar-bench export --rosbag2 makes bags of any run)
    ros2: int | None = None
    ros2_args: tuple = ()  # flags for the ros2 node (its topics' rates)
    attach: bool = False  # the services are already running (docker-compose): do not spawn them
    # SCHED_FIFO (where permitted) for the two ends of the FRI link, the robot above the
    # commander; the others stay ordinary processes.  All six at one priority starve
    # one another on two cores (measured: 97 % missed deadlines)
    sched_fifo: bool = False
    # (role, priority) used with sched_fifo: the chain's two ends at their priorities in it
    fifo_priorities: tuple = tuple((r, p) for r, p in FIFO_CHAIN if r in ("robot", "impedance_commander"))
    # the robot on the last CPU, every other service on the others: the 1 kHz loop keeps
    # most of a core (and its caches) instead of sharing it with five processes that each
    # wake a thousand times a second
    isolate_robot: bool = False
    ready_timeout: float = 60.0
    learn_threads: int | None = None  # numba threads for learning; None: the CPUs this process may use
    # processes for the run's own independent work (the candidate fits of a phase-count
    # selection, reading the recordings for the report); None: one per CPU; a sweep gives 1
    workers: int | None = None
    # with the realtime clock: what to ask of the machine (services.run.realtime_profile);
    # sched_fifo / isolate_robot above add to it with their own priorities
    realtime_profile: str = "auto"
    # an ``out`` that already holds a run is refused unless this says to remove that run first
    replace: bool = False
    # the command the report names (None: this process's command line)
    command: str | None = None
    # etar-bench serve: the cell alone for a lab's FRI remote and Net F/T client, instead of
    # the scenario's stages (services.run.serve.ServeOptions)
    serve: object | None = None
    # udp: the KRC and the commander over FRI 1.0/UDP, the estimator reading the Net F/T box
    # (services.run.wire); realtime over Zenoh on one host only
    wire: str = "zenoh"

    def __post_init__(self):
        if self.transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {', '.join(TRANSPORTS)}, got {self.transport!r}")
        if self.run_id is not None:
            topics.check_run_id(self.run_id)
        parse_profile(self.realtime_profile)
        if self.foxglove is not None:
            if not (0 <= self.foxglove <= 65535):
                raise ValueError(f"--foxglove PORT must be in 0..65535 (0: any free port), got {self.foxglove}")
            if self.tls is not None or self.hosts is not None or self.attach:
                raise ValueError("--foxglove cannot be combined with --tls, --hosts or --attach yet: the bridge "
                                 "would need credentials and a host of its own")
        in_process = self.transport == "inproc"
        check_engine(self.engine, in_process)
        if self.ros2 is not None:
            check_domain(self.ros2, "--ros2 DOMAIN")
            if in_process or self.tls is not None or self.hosts is not None or self.attach:
                raise ValueError("--ros2 puts the cell on ROS 2's Zenoh wire beside the services' own: it needs "
                                 "--transport zenoh and cannot be combined with --tls, --hosts or --attach yet")
        if self.attach and in_process:
            raise ValueError("--attach drives services already running over Zenoh; it cannot be combined with "
                             "--transport inproc")
        if self.hosts is not None and (in_process or self.zenoh is not None or self.attach):
            raise ValueError("--hosts starts the services on hosts of this machine over Zenoh: it cannot be "
                             "combined with --transport inproc, --connect or --attach")
        if self.tls is not None and (in_process or self.zenoh is not None or self.attach):
            raise ValueError("--tls makes the runner the run's router over Zenoh: it cannot be combined with "
                             "--transport inproc, --connect or --attach")
        if self.attach and (self.zenoh is None or not self.run_id):
            raise ValueError("--attach needs --connect (the router or a peer) and --run-id (the services')")
        if not (isinstance(self.ready_timeout, (int, float)) and math.isfinite(self.ready_timeout)
                and self.ready_timeout > 0):
            raise ValueError(f"--ready-timeout must be a number of seconds > 0, got {self.ready_timeout!r}")
        if self.wire not in WIRES:
            raise ValueError(f"--wire must be one of {', '.join(WIRES)}, got {self.wire!r}")
        if self.wire == "udp" and (in_process or self.hosts is not None or self.attach or self.tls is not None):
            raise ValueError("--wire udp puts the robot, the commander, the sensor and the estimator on loopback "
                             "UDP: it cannot be combined with --transport inproc, --hosts, --attach or --tls")
        for name in ("workers", "learn_threads"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


    def roles(self, scenario: Scenario) -> list[str]:
        """The services this run needs: the scenario's (serving: the cell alone), the live
        view's bridge and the cell's ROS 2 node."""
        roles = list(CELL_ROLES) if self.serve is not None else list(scenario.roles)
        return (roles + (["foxglove_bridge"] if self.foxglove is not None else [])
                + (["ros2"] if self.ros2 is not None else []))

    def carrier(self, scenario: Scenario):
        """The transport (``services.transport.carriers``), checked against the scenario's clock
        and the run's roles: every option and every credential before anything starts."""
        if self.foxglove:
            port_free(self.foxglove)
        chosen = carrier(self.transport, self.roles(scenario), zenoh=self.zenoh, tls=self.tls, hosts=self.hosts,
                         attach=self.attach, engine=self.engine)
        if self.wire == "udp" and scenario.clock != "realtime":
            raise ScenarioError("--wire udp needs the realtime clock (--clock realtime): the KRC sends on its own "
                                "clock and the remote answers on the wall clock", path="clock",
                                value=scenario.clock, source=scenario.source)
        if scenario.clock not in chosen.clocks:
            raise ScenarioError(f"the {chosen.describe()} transport runs {' or '.join(chosen.clocks)} only; "
                                "use --transport zenoh for realtime", path="clock", value=scenario.clock,
                                source=scenario.source)
        return chosen


def port_free(port: int, host: str = "127.0.0.1") -> None:
    """Refuse a live-view port that is taken before anything starts (the bridge would
    only find out once the services are up)."""
    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ValueError(f"--foxglove {port}: {host}:{port} is taken ({exc.strerror}); choose another port, "
                             "or 0 for any free one") from None


def check_cluster(address: str) -> None:
    """ValueError unless Dask distributed is installed and ``address`` is a scheduler's as it
    reads one, ``[SCHEME://]HOST:PORT`` (tcp when no scheme): before anything is made."""
    try:
        from distributed.comm.addressing import parse_address
        from distributed.comm.registry import get_backend
    except ImportError:
        raise ValueError("--cluster needs Dask distributed: pip install 'etar-testbench[cluster]' "
                         "(make run and make test install it)") from None
    try:
        scheme, location = parse_address(address)
        get_backend(scheme)  # ValueError naming the schemes it knows
        host, colon, port = location.rpartition(":")
        problem = ("" if scheme == "inproc" else "no HOST:PORT" if not colon or not host
                   else "" if port.isdigit() and 1 <= int(port) <= 65535 else f"port {port!r} is not in 1..65535")
    except ValueError as exc:
        problem = str(exc)
    if problem:
        raise ValueError(f"--cluster {address or repr(address)}: {problem}; expected a Dask scheduler's address, e.g. "
                         "tcp://10.0.0.5:8786")
