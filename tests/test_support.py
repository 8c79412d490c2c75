"""The tests' own helpers, where a wrong one would make other tests pass or fail for
reasons of their own."""

import signal
import subprocess
import sys

import pytest

from tests.support import assert_a_stall, popen_as_from_a_terminal

SAYS_SIGINT = [sys.executable, "-c", "import signal; print(signal.getsignal(signal.SIGINT))"]


def test_a_child_started_as_from_a_terminal_sees_ctrl_c_even_when_the_tests_were_started_ignoring_it():
    """pytest started as a background job of a script inherits SIGINT ignored (bash does
    that without job control); the runner a Ctrl-C test starts must not."""
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        plain = subprocess.run(SAYS_SIGINT, capture_output=True, text=True, check=True).stdout.strip()
        child = popen_as_from_a_terminal(SAYS_SIGINT, stdout=subprocess.PIPE, text=True)
        said = child.communicate(timeout=30)[0].strip()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # the parent's own is put back
    finally:
        signal.signal(signal.SIGINT, before)
    assert plain == "1"  # SIG_IGN: what the Ctrl-C tests' runner had when one ran to its end
    assert said == "<built-in function default_int_handler>"


# the realtime tests' judge of a stalling machine: what it lets through as a stall, to be
# retried or skipped, and what it fails
def fri(answered: int, missed: int, entered: int) -> dict:
    return {"answered": answered, "missed": missed, "command_mode_entered": entered}


@pytest.mark.parametrize("figures", [fri(9_990, 10, 1), fri(9_000, 1_000, 3),
                                     # never in command mode: a miss every 94 cycles (CI on 840142a)
                                     fri(14_842, 158, 0)])
def test_a_machine_that_stalls_now_and_then_is_a_stall(figures):
    assert_a_stall(figures, "fell short")


@pytest.mark.parametrize("figures, said", [
    (fri(5_000, 5_000, 1), "too many cycles unanswered"),  # a remote that answers half the time
    (fri(0, 15_000, 0), "too many cycles unanswered"),  # a remote that never answers
    # command mode withheld from a remote that missed once every 1 500 cycles: the KRC's fault
    (fri(14_990, 10, 0), "command mode never entered though a miss came only every 1500 cycles"),
])
def test_what_is_not_a_stall_fails(figures, said):
    with pytest.raises(AssertionError, match=said):
        assert_a_stall(figures, "fell short")
