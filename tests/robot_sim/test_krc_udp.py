"""The simulated KRC over real UDP sockets on loopback, driven by a remote through the KRL
programs of both public conventions (frilibrary, lwr_hw): command mode entered and left,
the motion commanded followed, strategies refused, a first command that jumps refused,
the KRC streaming OFF after a close.  The KRC side waits for each answer
(``UdpKrc.take(m, timeout)``), so the exchange does not depend on the machine's timing.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from robot_sim.cell import RobotCell
from robot_sim.krc.faults import LinkFaults
from robot_sim.krc.link import FriConfig
from robot_sim.krc.packets import ControlMode, FriQuality, FriState
from robot_sim.wire.fri_datagrams import CommandFlags
from services.transport.lab.krc_udp import UdpKrc
from robot_sim.krc.krl import OFF_STREAM_S, REFUSAL_INDEX
from robot_sim.world.teacher import DOWN
from robot_sim.world.tasks import free_space
from tests.robot_sim.fri_remote import Remote

# the KRC answering at 1 kHz over UDP: alone (make test runs these first, with nothing beside them)
pytestmark = [pytest.mark.serial, pytest.mark.alone]

START = np.array([0.5, 0.0, 0.45])
LATENCY_NS = 200_000  # each answer taken to arrive 0.2 ms into its cycle


@pytest.fixture
def cell():
    c = RobotCell(free_space(), seed=3, with_sensor=False)
    c.place_tcp(START, DOWN)
    c.start()
    return c


def run(krc: UdpKrc, cycles: int, until=None) -> int:
    """``cycles`` KRC cycles (fewer if ``until()`` turns true); the cycles run."""
    cell = krc.cell
    for k in range(cycles):
        m = cell.begin_cycle()
        krc.send(m)
        krc.take(m, timeout_s=0.5, latency_ns=LATENCY_NS)
        cell.end_cycle()
        if until is not None and until():
            return k + 1
    return cycles


def tcp(cell) -> np.ndarray:
    return cell.sim.tcp_position()


def move_x(distance: float, seconds: float):
    """Cartesian impedance: from the pose command mode began at, a smooth move along base x."""
    state = {}

    def command(m):
        pose = np.array(m["data"]["msrCartPos"], dtype=np.float64)
        if "t0" not in state:
            state["t0"], state["pose"] = float(m["intf"]["timestamp"]), pose.copy()
        s = min(1.0, (float(m["intf"]["timestamp"]) - state["t0"]) / seconds)
        target = state["pose"].copy()
        target[3] += distance * (10 * s**3 - 15 * s**4 + 6 * s**5)
        return CommandFlags.CART_IMP, {"cartPos": target}
    return command


@pytest.mark.parametrize("krl", ["frilibrary", "lwr_hw"])
def test_a_remote_starts_command_mode_moves_the_arm_and_stops(cell, krl):
    with Remote(krl, strategy=20) as remote, UdpKrc(cell, ("127.0.0.1", remote.port), krl=krl) as krc:
        run(krc, 300)
        assert cell.fri.state == FriState.MON and remote.received == 300
        assert remote.krl_state == 10  # both programs report 10 once FRI is open
        x0 = tcp(cell).copy()
        remote.command = move_x(0.02, 1.0)
        remote.request = "start"
        cycles = run(krc, 2000, until=lambda: cell.fri.state == FriState.CMD)
        assert cell.fri.state == FriState.CMD, cycles
        run(krc, 5)
        assert remote.krl_state == (20 if krl == "frilibrary" else 1)
        run(krc, 1500)
        moved = tcp(cell) - x0
        assert moved[0] == pytest.approx(0.02, abs=2e-3) and abs(moved[1]) < 2e-3 and abs(moved[2]) < 2e-3
        remote.request = "stop"
        run(krc, 200, until=lambda: cell.fri.state == FriState.MON)
        run(krc, 60)
        assert cell.fri.state == FriState.MON
        assert remote.krl_state == (10 if krl == "frilibrary" else 0)
        kinds = [e.kind for e in krc.krl.events]
        assert kinds == ["open", "start", "started", "stop"]
        c = krc.endpoint.counters
        assert c.wrong_size == c.wrong_id == c.invalid == c.late == 0 and c.accepted == c.sent


def test_frilibrary_close_streams_off_then_opens_again_with_the_other_close_value(cell):
    with Remote("frilibrary") as remote, UdpKrc(cell, ("127.0.0.1", remote.port)) as krc:
        run(krc, 100)
        assert remote.to_int(15) == 30
        remote.request = "close"
        run(krc, 100, until=lambda: krc.krl.streaming_off)
        run(krc, 5)
        assert remote.krl_state == 30 and int(remote.last["intf"]["state"]) == FriState.OFF
        remote.request = None
        run(krc, int(OFF_STREAM_S * 1000) + 10)
        # opened again: monitor mode, the close value alternates so a stale close cannot close this run
        assert int(remote.last["intf"]["state"]) == FriState.MON and remote.to_int(15) == 40
        assert [e.kind for e in krc.krl.events] == ["open", "close", "open"]
        assert (FriState.OFF, 30) in remote.states


@pytest.mark.parametrize("strategy", [90, 40])
def test_a_strategy_the_krc_does_not_run_is_refused_in_monitor_mode(cell, strategy):
    with Remote("frilibrary", strategy=strategy) as remote, UdpKrc(cell, ("127.0.0.1", remote.port)) as krc:
        run(krc, 300)
        remote.request = "start"
        run(krc, 600)
        assert cell.fri.state == FriState.MON and remote.krl_state == 10
        assert remote.to_int(REFUSAL_INDEX) == strategy
        assert f"strategy {strategy}" in krc.krl.refusal
        assert [e.kind for e in krc.krl.events].count("refused") == 1  # not repeated at every poll


def test_a_first_command_that_jumps_is_refused_and_the_link_drops_to_monitor(cell):
    with Remote("frilibrary", strategy=20) as remote, UdpKrc(cell, ("127.0.0.1", remote.port)) as krc:
        run(krc, 300)
        x0 = tcp(cell).copy()

        def jump(m):
            pose = np.array(m["data"]["msrCartPos"], dtype=np.float64)
            pose[3] += 0.05
            return CommandFlags.CART_IMP, {"cartPos": pose}
        remote.command = jump
        remote.request = "start"
        run(krc, 2000, until=lambda: bool(cell.first_command_refused))
        assert "first command 50.0 mm" in cell.first_command_refused
        run(krc, 2)
        assert cell.fri.state == FriState.MON
        assert np.linalg.norm(tcp(cell) - x0) < 1e-3  # nothing of the jump applied
        assert "fallback" in [e.kind for e in krc.krl.events]


def test_joint_position_streamed_every_cycle_is_followed(cell):
    with Remote("lwr_hw", strategy=10) as remote, UdpKrc(cell, ("127.0.0.1", remote.port), krl="lwr_hw") as krc:
        run(krc, 300)
        q0 = np.array(cell.sim.joint_positions())
        state = {}

        def wave(m):
            t = float(m["intf"]["timestamp"])
            state.setdefault("t0", t)
            state.setdefault("q", np.array(m["data"]["msrJntPos"], dtype=np.float64))
            q = state["q"].copy()
            q[0] += 0.2 * np.sin(np.pi * min(1.0, (t - state["t0"]) / 2.0) / 2)  # 0 -> 0.2 rad in 2 s
            return CommandFlags.POSITION, {"jntPos": q}
        remote.command = wave
        remote.request = "start"
        run(krc, 2000, until=lambda: cell.fri.state == FriState.CMD)
        assert cell.krc.mode == ControlMode.POSITION
        run(krc, 2500)
        q = np.array(cell.sim.joint_positions())
        assert q[0] - q0[0] == pytest.approx(0.2, abs=5e-3)
        assert np.all(np.abs(q[1:] - q0[1:]) < 5e-3)


def test_joint_impedance_holds_with_the_commanded_stiffness(cell):
    """JNT_IMP: a torque added on joint 4 deflects it by tau / k (gravity compensated)."""
    with Remote("frilibrary", strategy=30) as remote, UdpKrc(cell, ("127.0.0.1", remote.port)) as krc:
        run(krc, 300)
        state = {}

        def push(m):
            state.setdefault("q", np.array(m["data"]["msrJntPos"], dtype=np.float64))
            k = np.full(7, 1000.0)
            k[3] = 200.0
            torque = np.zeros(7)
            torque[3] = 4.0
            return CommandFlags.JNT_IMP, {"jntPos": state["q"], "jntStiffness": k, "jntDamping": np.full(7, 0.7),
                                          "addJntTrq": torque}
        remote.command = push
        remote.request = "start"
        run(krc, 2000, until=lambda: cell.fri.state == FriState.CMD)
        assert cell.krc.mode == ControlMode.JNT_IMP
        run(krc, 3000)
        q = np.array(cell.sim.joint_positions())
        deflection = q - state["q"]
        assert deflection[3] == pytest.approx(4.0 / 200.0, rel=0.15)
        assert np.all(np.abs(np.delete(deflection, 3)) < 2e-3)


def test_rotational_stiffness_goes_in_a_b_c_order(cell):
    """A (about z) soft, B and C stiff: a torque about the tool's z turns it by Tz / A; the
    same torque about x barely turns it.  Swapping the order would swap the two."""
    with Remote("frilibrary", strategy=20) as remote, UdpKrc(cell, ("127.0.0.1", remote.port)) as krc:
        remote.stiffness = np.array([3000.0, 3000.0, 3000.0, 20.0, 300.0, 300.0])  # x y z A B C
        run(krc, 300)
        R0 = cell.sim.tcp_rotation().copy()
        state = {}

        def twist(m):
            state.setdefault("pose", np.array(m["data"]["msrCartPos"], dtype=np.float64))
            ft = np.zeros(6)
            ft[3] = 1.0  # Tz, FRI order Fx Fy Fz Tz Ty Tx
            ft[5] = 1.0  # Tx
            return CommandFlags.CART_IMP, {"cartPos": state["pose"], "addTcpFT": ft,
                                           "cartStiffness": remote.stiffness}
        remote.command = twist
        remote.request = "start"
        run(krc, 2000, until=lambda: cell.fri.state == FriState.CMD)
        run(krc, 3000)
        rot = pin.log3(R0.T @ cell.sim.tcp_rotation())  # in the tool's axes
        assert rot[2] == pytest.approx(1.0 / 20.0, rel=0.2)
        assert abs(rot[0]) < 1.0 / 300.0 * 2


def test_a_safety_stop_drops_the_remote_to_monitor_mode_and_shows_in_the_measurement(cell):
    """A pose far off in command mode (not the first command, which would be refused):
    the torques saturate, the KRC stops the arm, drops the link to monitor mode and sets
    robot.error, which the remote reads."""
    with Remote("frilibrary", strategy=20) as remote, UdpKrc(cell, ("127.0.0.1", remote.port)) as krc:
        run(krc, 300)
        state = {}

        def far(m):
            state["n"] = state.get("n", 0) + 1
            pose = np.array(m["data"]["msrCartPos"], dtype=np.float64)
            if state["n"] > 10:
                pose[3] += 0.5
            return CommandFlags.CART_IMP, {"cartPos": pose, "cartStiffness": np.full(6, 300.0)}
        remote.command = far
        remote.request = "start"
        run(krc, 2000, until=lambda: cell.fri.state == FriState.CMD)
        run(krc, 3000, until=lambda: cell.krc.safety != 0)
        assert cell.krc.safety != 0 and not cell.first_command_refused
        run(krc, 3)
        assert cell.fri.state == FriState.MON
        assert int(remote.last["robot"]["error"]) == int(cell.krc.safety)
        assert int(remote.last["intf"]["state"]) == FriState.MON


def test_the_link_faults_act_on_the_udp_link_too():
    """Commands that crossed the socket still go through the link's fault model: with a
    fifth of them dropped, FRI misses about a fifth of the cycles the remote answered."""
    cell = RobotCell(free_space(), seed=3, with_sensor=False, faults=LinkFaults(seed=1, drop_probability=0.2))
    cell.place_tcp(START, DOWN)
    cell.start()
    with Remote("frilibrary") as remote, UdpKrc(cell, ("127.0.0.1", remote.port)) as krc:
        run(krc, 1000)
        stats = cell.fri.statistics()
        assert krc.endpoint.counters.accepted == 1000  # every answer arrived on the socket
        assert 120 < stats.missed < 280 and stats.answered == 1000 - stats.missed
        assert cell.fri.quality < FriQuality.OK


def test_a_four_millisecond_cycle_as_fri_open_4_sets_it():
    """friOpen(4): a measurement every 4 ms, saying so in desiredMsrSampleTime; the KRC's
    own control still runs every 1 ms physics step, and the remote's move is followed."""
    cell = RobotCell(free_space(), seed=3, with_sensor=False, fri_config=FriConfig(cycle_ns=4_000_000))
    cell.place_tcp(START, DOWN)
    cell.start()
    with Remote("frilibrary", strategy=20) as remote, UdpKrc(cell, ("127.0.0.1", remote.port)) as krc:
        run(krc, 100)
        assert float(remote.last["intf"]["desiredMsrSampleTime"]) == pytest.approx(0.004)
        assert float(remote.last["intf"]["timestamp"]) == pytest.approx(99 * 0.004, abs=1e-6)
        x0 = tcp(cell).copy()
        remote.command = move_x(0.02, 1.0)
        remote.request = "start"
        run(krc, 600, until=lambda: cell.fri.state == FriState.CMD)
        assert cell.fri.state == FriState.CMD
        run(krc, 400)  # 1.6 s
        assert (tcp(cell) - x0)[0] == pytest.approx(0.02, abs=2e-3)
    with pytest.raises(ValueError, match="whole number of physics steps"):
        RobotCell(free_space(), fri_config=FriConfig(cycle_ns=1_500_000))
