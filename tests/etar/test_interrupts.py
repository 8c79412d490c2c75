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
