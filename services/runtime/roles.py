"""The roles of a run, once: which node plays each, the program that carries it alone, the
FRI cycle participant it answers for, its SCHED_FIFO priority in the realtime chain,
and whether a restart mid-run is meaningful.  Every layer reads this table (the
nodes' registry, the launcher, the cycle engine, the realtime profile, the
credentials, the scenario's restart policies) instead of keeping a list of its own.
"""

from __future__ import annotations

from dataclasses import dataclass

from services.runtime.messages import ESTIMATOR_PHASE, FT_WRENCH, ROBOT_COMMAND, TEACHER_WRENCH


@dataclass(frozen=True)
class Role:
    name: str
    what: str
    # the FRI cycle participant this role answers for (the cycle engine waits for it) and
    # the topic its answer comes on; None: the robot does not wait for it
    answers: str | None = None
    answer_topic: str | None = None
    # SCHED_FIFO priority in the realtime profile's chain: the robot above whoever answers
    # its cycles (the commander in a reproduction, the teacher in a demonstration; never
    # both at once), the sensor and the estimator below; None: an ordinary process (the
    # recorder needs every message, not each one at once)
    fifo_priority: int | None = None
    # a restart mid-run is meaningful: the recorder (a new file, the gap reported) and the
    # estimator (its filter re-synchronised); the others hold state a restart would lose
    # (the robot's FRI session, the sensor's tare, the commander's and the teacher's episode)
    restartable: bool = False
    # over Zenoh its subscriptions are declared only while it listens, in lockstep too:
    # every input it has comes from the robot, which waits for its listening token
    # (topics.listening) before an episode's first cycle.  Idle, its messages would still
    # cost a lockstep run CPU (docs/benchmarks.md says how much); a role fed by another (the commander
    # by the estimator) would need that one to wait as well
    subscribes_when_listening: bool = False

    @property
    def program(self) -> str:
        """The console script that runs this role in its own process."""
        return "etar-" + self.name.replace("_", "-")


ROLES: dict[str, Role] = {r.name: r for r in (
    Role("robot", "the LWR4+ behind its KRC: physics, FRI, the 1 kHz cycle", fifo_priority=60),
    Role("ft_sensor", "the ATI force/torque sensor", answers="ft", answer_topic=FT_WRENCH.topic, fifo_priority=50),
    Role("teacher", "the simulated teacher's hand (demonstrations)", answers="teacher",
         answer_topic=TEACHER_WRENCH.topic, fifo_priority=55, subscribes_when_listening=True),
    Role("phase_estimator", "the online ETAR filter (100 Hz)", answers="phase", answer_topic=ESTIMATOR_PHASE.topic,
         fifo_priority=45, restartable=True),
    Role("impedance_commander", "the per-phase Cartesian impedance command (1 kHz)", answers="command",
         answer_topic=ROBOT_COMMAND.topic, fifo_priority=55),
    Role("recorder", "one MCAP file per episode", restartable=True),
    Role("foxglove_bridge", "the live view over Foxglove's WebSocket protocol"),
    Role("ros2", "the cell as a ROS 2 node on rmw_zenoh's wire"),
)}

# the cell every run has (a serve has only these), and the roles each kind of stage adds
CELL_ROLES = ("robot", "ft_sensor", "recorder")
STAGE_ROLES = {"demonstrate": ("teacher",), "learn": (), "reproduce": ("phase_estimator", "impedance_commander")}

# the cycle participants in the order the robot has always listed them, and who answers for each
PARTICIPANTS: dict[str, str] = {r.answers: r.name for r in sorted(
    (r for r in ROLES.values() if r.answers), key=lambda r: ("command", "teacher", "ft", "phase").index(r.answers))}
RESTARTABLE = tuple(r.name for r in ROLES.values() if r.restartable)
FIFO_CHAIN = tuple(sorted(((r.name, r.fifo_priority) for r in ROLES.values() if r.fifo_priority is not None),
                          key=lambda rp: -rp[1]))
# the identity a credential is issued to: the runner beside the roles
# (the live view and the ROS 2 node do not run under credentials: --tls refuses them)
CREDENTIAL_NAMES = ("runner", *(r for r in ROLES if r not in ("foxglove_bridge", "ros2")))


def role(name: str) -> Role:
    """The role called ``name``; ValueError naming the known ones otherwise."""
    try:
        return ROLES[name]
    except KeyError:
        raise ValueError(f"unknown role {name!r} (roles: {', '.join(ROLES)})") from None
