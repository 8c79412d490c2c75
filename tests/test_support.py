"""The tests' own helpers, where a wrong one would make other tests pass or fail for
reasons of their own."""

import signal
import subprocess
import sys

from tests.support import popen_as_from_a_terminal

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
