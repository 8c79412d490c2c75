"""How many threads learning may use.

numba's parallel E-step spreads over every CPU it is allowed; when other work
shares those CPUs its workers wait on each other (measured on a fresh clone: the
valley's learn stage took 448 s while other processes ran, 28 s on a quiet
machine).  A sweep runs many learners at once, so each gets one thread and the
parallelism comes from running several at a time.
"""

from __future__ import annotations

import contextlib
import os


def available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


@contextlib.contextmanager
def learning_threads(n: int | None):
    """numba's thread count inside the block: ``n``, or the CPUs this process may use."""
    import numba

    want = max(1, min(int(n) if n else available_cpus(), numba.config.NUMBA_NUM_THREADS))
    before = numba.get_num_threads()
    numba.set_num_threads(want)
    try:
        yield want
    finally:
        numba.set_num_threads(before)
