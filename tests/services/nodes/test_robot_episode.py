"""The robot's episode judge as a function of its cycles' outcomes: no physics, no bus."""

from types import SimpleNamespace

import numpy as np

from robot_sim.krc.packets import FriQuality, FriState
from services.nodes.robot_episode import HOLD_WATCH_CYCLES, EpisodeJudge
from services.runtime.messages import HOLD_WATCH_S


class Link:
    def __init__(self):
        self.state, self.command_requested, self.requests = FriState.CMD, True, 0

    def request_command_mode(self):
        self.requests += 1
        self.command_requested = True


def cell(x=0.0, safety=0):
    return SimpleNamespace(fri=Link(), krc=SimpleNamespace(safety=safety), first_command_refused="",
                           sim=SimpleNamespace(tcp_position=lambda: np.array([x, 0.0, 0.0])),
                           contact_force=np.array([3.0, 4.0, 0.0]))


def outcome(state=FriState.CMD, answered=True):
    return SimpleNamespace(state=state, quality=FriQuality.PERFECT, answered=answered)


def judge():
    return EpisodeJudge(1, SimpleNamespace(state=FriState.MON), 0, 1_000_000)


def test_a_hold_ends_the_episode_after_the_hold_watch_and_records_what_the_arm_did():
    ep, c = judge(), cell()
    reasons = [ep.judge(c, outcome(), seq, kind="reproduction", stop_on=None, teacher_done=False,
                        goal_reached=False, hold="stale_estimate", estimate_seq=5, track_states=False)
               for seq in range(1, HOLD_WATCH_CYCLES + 1)]
    assert HOLD_WATCH_CYCLES == round(HOLD_WATCH_S * 1000)
    assert reasons[:-1] == [None] * (HOLD_WATCH_CYCLES - 1) and reasons[-1] == "hold:stale_estimate"
    assert ep.hold["seq"] == 1 and ep.hold["at_s"] == 0.0 and ep.hold["cycles"] == HOLD_WATCH_CYCLES
    assert ep.hold["peak_contact_force"] == 5.0 and ep.cmd_entered == 1 and ep.cmd_cycles == HOLD_WATCH_CYCLES


def test_a_command_that_stops_holding_restarts_the_watch():
    ep, c = judge(), cell()
    for seq in range(1, HOLD_WATCH_CYCLES):
        hold = "" if seq == HOLD_WATCH_CYCLES // 2 else "gap"
        assert ep.judge(c, outcome(), seq, kind="reproduction", stop_on=None, teacher_done=False,
                        goal_reached=False, hold=hold, estimate_seq=-1, track_states=False) is None
    assert ep.hold_run == HOLD_WATCH_CYCLES - 1 - HOLD_WATCH_CYCLES // 2


def test_the_goal_and_the_teacher_end_it_only_when_asked_and_safety_always():
    ep, c = judge(), cell()
    kw = dict(kind="reproduction", hold=None, estimate_seq=-1, track_states=True)
    assert ep.judge(c, outcome(), 1, stop_on="teacher_done", teacher_done=False, goal_reached=True, **kw) is None
    assert ep.judge(c, outcome(), 2, stop_on="goal_reached", teacher_done=False, goal_reached=True, **kw) \
        == "goal_reached"
    assert ep.judge(cell(safety=1), outcome(), 3, stop_on=None, teacher_done=False, goal_reached=False, **kw) \
        .startswith("safety:")
    assert ep.states == [(1, int(FriState.CMD), int(FriQuality.PERFECT))]


def test_a_reproduction_that_fell_back_to_monitor_mode_asks_for_command_mode_again():
    ep, c = judge(), cell()
    c.fri.state, c.fri.command_requested = FriState.MON, False
    ep.judge(c, outcome(FriState.MON, answered=False), 1, kind="reproduction", stop_on=None, teacher_done=False,
             goal_reached=False, hold=None, estimate_seq=-1, track_states=False)
    assert c.fri.requests == 1 and ep.miss_run == 1
