"""A Ctrl-C (or a SIGTERM taken as one) that arrives while compiled code runs.

Python takes a signal between bytecodes; numba's machine code has none, so the handler's
KeyboardInterrupt is raised at the first C-API call that checks for signals inside a
kernel's call (scipy's optimiser calling the EM objective, a dispatcher typing an
argument), and the dispatcher, finding an exception set beside its result, raises
``SystemError("... returned a result with an exception set")`` with the KeyboardInterrupt
as its cause.  Whoever tells an interrupt from a failure asks ``interrupt_behind``.
"""

from __future__ import annotations


def interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt that ``exc`` is, or that a SystemError of compiled code was
    raised from (its cause or context, followed a few links); None for any other exception."""
    seen = 0
    while exc is not None and seen < 8:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        if not isinstance(exc, SystemError):
            return None
        exc, seen = exc.__cause__ or exc.__context__, seen + 1
    return None
