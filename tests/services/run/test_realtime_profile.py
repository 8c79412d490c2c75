"""The realtime profile (what a run asks of the machine), the verdict on whether a run held
its clock, and realtime nodes that stop their inputs while they have nothing to do."""

import threading
import time

import pytest

from services.nodes.teacher import TeacherConfig, TeacherNode
from services.run.realtime_profile import PARTS, parse_profile, probe
from services.results.report import REALTIME_MISS_LIMIT, clock_not_held
from services.runtime import topics
from services.runtime.bus import MonotonicClock
from services.transport.process import NodeInputs, ZenohBus
from tests.services.conftest import service_with_peer
from tests.support import wait_until

# SCHED_FIFO, CPU isolation and /dev/cpu_dma_latency of this machine: alone (make test runs these first, with nothing beside them)
pytestmark = [pytest.mark.serial, pytest.mark.alone]


def test_profile_parts_parse_and_a_bad_part_is_named():
    assert parse_profile("auto") == frozenset(PARTS)
    assert parse_profile("none") == frozenset()
    assert parse_profile(" fifo , isolate ") == {"fifo", "isolate"}
    with pytest.raises(ValueError, match=r"realtime profile 'fifo,turbo': unknown part 'turbo'"):
        parse_profile("fifo,turbo")


def test_probe_says_for_every_part_whether_it_was_granted_and_why_not():
    grant = probe(frozenset(PARTS))
    try:
        assert grant.granted | set(grant.refused) == set(PARTS)
        assert not grant.granted & set(grant.refused)
        if grant.refused:
            warning = grant.warning()
            assert all(f"{p} refused" in warning for p in grant.refused)
        else:
            assert grant.warning() is None
        assert grant.to_dict()["requested"] == sorted(PARTS)
    finally:
        grant.release()
    assert grant._qos_fd is None


def loop(cycles, misses):
    return {"cycles": cycles, "misses": misses}


def repro(index, answered, missed, first_cmd_s=0.6, left=0):
    return {"index": index, "fri": {"answered": answered, "missed": missed, "command_mode_left": left},
            "fri_quality": {"first_cmd_s": first_cmd_s}}


def test_a_run_that_held_its_clock_passes():
    assert clock_not_held([{}], [repro(0, 14990, 10)], [loop(4000, 3), loop(15000, 10)], {}) is None


def test_a_run_that_did_not_hold_its_clock_says_what_was_missed_and_which_link_was_late():
    received = {"robot/command -> robot": {"latency": {"count": 100, "p99_us": 1833.0}},
                "robot/state -> impedance_commander": {"latency": {"count": 100, "p99_us": 684.0}},
                "robot/contact -> recorder": {"latency": {"count": 100, "p99_us": 99999.0}}}  # not on the FRI chain
    why = clock_not_held([{}], [repro(0, 10434, 4566, first_cmd_s=None)], [loop(4072, 65), loop(15000, 100)],
                         received)
    assert why.startswith(f"the realtime clock was not held (limit {REALTIME_MISS_LIMIT:.0%} of cycles)")
    assert "demonstration 0: the robot loop missed 65 of 4072 deadlines (1.6%)" in why
    assert "reproduction 0: FRI never reached command mode, 4566 of 15000 FRI cycles unanswered in time (30.4%)" \
        in why
    assert why.endswith("latest link robot/command -> robot (p99 1833 us)")
    assert "\n" not in why


def test_a_reproduction_dropped_from_command_mode_did_not_hold_the_clock_however_few_its_misses():
    """1.0 % missed is within the limit, but bursts of them dropped command mode twice and the
    arm was held short of the goal (CI on dbf6c7c, over FRI/UDP): the machine, not the model."""
    why = clock_not_held([{}], [repro(0, 14850, 150, left=2)], [loop(4000, 3), loop(15000, 12)], {})
    assert why == (f"the realtime clock was not held (limit {REALTIME_MISS_LIMIT:.0%} of cycles): reproduction 0: "
                   "the KRC dropped command mode 2 time(s) (FRI quality below OK)")


@pytest.fixture
def teacher_service():
    with service_with_peer("teacher", "inputs") as parts:
        yield parts


def matched_within(publisher, want: bool, timeout: float = 10.0) -> bool:
    """Whether ``publisher`` reaches a subscriber (``want``) within ``timeout``."""
    changed = threading.Event()
    listener = publisher.declare_matching_listener(lambda status: status.matching == want and changed.set())
    try:
        return publisher.matching_status.matching == want or changed.wait(timeout)
    finally:
        listener.undeclare()


@pytest.mark.parametrize("clock", ["realtime", "lockstep"])
@pytest.mark.zenoh
def test_an_idle_teacher_takes_no_messages_and_says_when_it_listens(teacher_service, clock):
    """Idle, the teacher has no subscriber at all, on either clock; reset for a
    demonstration it subscribes, then declares its listening token for that episode (what
    the robot waits for in lockstep before the first cycle: services.transport.process)."""
    from services.transport.process import Listeners

    svc, run_id, robot = teacher_service
    node = TeacherNode(TeacherConfig(), ZenohBus(svc, clock == "realtime"), MonotonicClock(), mode=clock)
    inputs = NodeInputs(node, svc, realtime=clock == "realtime")
    inputs.sync()
    reset, idle = inputs.after(node.handlers()["reset"]), inputs.after(node.handlers()["idle"])
    state = robot.declare_publisher(topics.key(run_id, "robot/state"))
    listeners = Listeners(svc)
    try:
        # before its first demonstration the teacher has nothing to answer: no subscriber at all
        assert not node.listening and inputs.declared == []
        assert matched_within(state, False)
        token = reset({"start": [0.6, 0.0, 0.3], "episode": 4})["listening"]
        assert token.startswith(topics.listening(run_id, "teacher", "4."))
        assert node.listening and len(inputs.declared) == 2
        assert matched_within(state, True)
        assert listeners.wait([token], 10.0) == []
        idle({})
        assert inputs.declared == []
        assert matched_within(state, False)
        # gone with the subscriptions: its deletion reaches this session a moment later, so it is
        # polled for (looked at once right after idle, it was still live 1 run in 6 with two busy
        # processes beside it)
        wait_until(lambda: listeners.wait([token], 0.0) == [token], 10.0, "the listening token gone")
    finally:
        state.undeclare()
