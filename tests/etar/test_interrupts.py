"""A Ctrl-C inside compiled code is told from a failure (etar.interrupts)."""

from etar.interrupts import interrupt_behind


def _raised_from(cause: BaseException) -> SystemError:
    try:
        try:
            raise cause
        except BaseException as exc:
            # what CPython's check of a C function's result raises: the pending exception as its cause
            raise SystemError("CPUDispatcher(<function f>) returned a result with an exception set") from exc
    except SystemError as exc:
        return exc


def test_a_keyboard_interrupt_behind_numbas_system_error_is_found():
    interrupt = KeyboardInterrupt("SIGTERM")
    assert interrupt_behind(_raised_from(interrupt)) is interrupt
    assert interrupt_behind(_raised_from(_raised_from(interrupt))) is interrupt
    assert interrupt_behind(interrupt) is interrupt


def test_any_other_failure_is_not_an_interrupt():
    assert interrupt_behind(_raised_from(ValueError("bad"))) is None
    assert interrupt_behind(SystemError("a bare one")) is None
    assert interrupt_behind(RuntimeError("x")) is None
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ValueError("a failure while handling it is a failure")
    except ValueError as exc:
        assert interrupt_behind(exc) is None


def test_ctrl_c_during_etar_learn_is_an_interrupt_wherever_it_lands(tmp_path):
    """SIGINT while EM fits (most of the time inside numba's code): 'interrupted', exit 130,
    never a SystemError traceback (it was one, exit 1, two times in three)."""
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    from tests.support import popen_as_from_a_terminal

    etar = str(Path(sys.executable).parent / "etar")
    subprocess.run([etar, "synth", "--out", str(tmp_path), "--demos", "3"], check=True, capture_output=True)
    demos = [str(tmp_path / f"demo_0{i}.npz") for i in range(3)]
    for delay in (0.3, 0.7):
        # (SIGINT at its default in the child, as typed at a terminal: under a shell that ignored it, the learn
        # would inherit that and run to its end, exit 0)
        proc = popen_as_from_a_terminal([etar, "learn", *demos, "--out", str(tmp_path / "m.json"), "--restarts",
                                         "20"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        seen = ""
        while "fit 1/" not in seen:  # into the fits (their progress lines), then the signal
            line = proc.stderr.readline()
            assert line, f"etar learn ended before its first fit: {seen}"
            seen += line
        time.sleep(delay)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 130, (proc.returncode, err)
        assert "Traceback" not in err and err.strip().endswith("etar learn: interrupted"), err
