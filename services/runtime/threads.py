"""How many threads learning may use, and a pool of processes for a run's independent work.

numba's parallel E-step spreads over every CPU it is allowed; when other work
shares those CPUs its workers wait on each other (measured on a fresh clone: the
valley's learn stage took 448 s while other processes ran, 28 s on a quiet
machine).  A sweep runs many learners at once, so each gets one thread and the
parallelism comes from running several at a time.
"""

from __future__ import annotations

import contextlib
import os
import threading
from concurrent.futures.process import BrokenProcessPool


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


def _spawning(pool_map, fn, *iterables):
    """``pool_map`` (which starts the pool's processes as it needs them) with SIGINT blocked
    meanwhile: the processes start with it blocked, until their ``_worker_start`` ignores it.
    Here a SIGINT waits until the work is handed over, then interrupts as ever."""
    import signal

    if threading.current_thread() is not threading.main_thread():
        return pool_map(fn, *iterables)
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        return pool_map(fn, *iterables)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def exit_without_teardown(code: int = 0) -> None:
    """End this process now with ``code``, its output flushed, skipping the interpreter's
    teardown of the modules its work brought (numba, SciPy, MuJoCo, Zenoh: 0.2-1.0 s, which
    whoever waits for the process to end waits for too).  For a process whose files and
    sessions are already closed: a pool's process (atexit, ``_worker_start``), the MCAP
    writer helper and a service process (their ``__main__``)."""
    import sys

    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(code)


def _worker_start(idle: bool = False) -> None:
    import atexit
    import signal

    import numba

    atexit.register(exit_without_teardown)

    numba.set_num_threads(1)
    # Ctrl-C is the runner's to handle: it ends the pool, a worker needs no traceback of its own.
    # Until here SIGINT was blocked (``_spawning``): a second Ctrl-C to the process group while
    # the report's pool started killed a worker half-way through its start-up, and the report
    # was lost to a BrokenProcessPool
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    if idle:
        # only CPU nobody else wants: beside a run on two cores its work slowed the run's
        # own processes (the valley's episodes 38.5 -> 45.6 s) more than it saved
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


@contextlib.contextmanager
def process_map(workers: int | None, beside: bool = False):
    """A ``map`` over independent pieces of a run's own work (the candidate fits of a
    phase-count selection, reading the recordings for the report): ``workers`` None,
    a pool of one single-threaded process per CPU this process may use; 1 (a sweep,
    whose parallelism is across runs), the builtin ``map`` in this process, or with
    ``beside`` a pool of one process under SCHED_IDLE (work that goes on while the run goes
    on, on the CPU it leaves).  Results come back in order, whatever runs where.  For the fits: numba's parallel E-step
    gains little on one demonstration's thousand steps (the valley's 36 candidate
    fits: 17.9 s on 2 threads, 19.4 s on one, 11.6 s in two processes)."""
    if beside:
        workers = 1
    else:
        workers = available_cpus() if workers is None else int(workers)
        if workers < 2:
            yield map
            return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # spawn: numba's threads and Zenoh's do not survive fork
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_start,
                               initargs=(beside,))
    try:
        yield PoolMap(pool)
    except BaseException:
        # interrupted or failed: no piece is worth waiting for, and none may outlive the run
        # (the executor has no public way to stop its workers before Python 3.14)
        processes = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.terminate()
        for process in processes:
            process.join(5)
        raise
    pool.shutdown()


class PoolMap:
    """A pool's ``map`` (results in order, as ``map``'s), and its ``submit`` for a piece whose
    caller may take it back while it has not begun (``Future.cancel``) and do it itself."""

    def __init__(self, pool):
        self._pool = pool

    def __call__(self, fn, *iterables):
        return _spawning(self._pool.map, fn, *iterables)

    def submit(self, fn, *args):
        return _spawning(self._pool.submit, fn, *args)


class FallbackMap:
    """A pool's ``map`` (``process_map``'s) whose pieces are done in this process once the
    pool is broken: a worker killed (by anyone, the OOM killer first) must not cost the run
    work that is a pure function of its input.  The pieces already returned stand; the rest
    are done here, in order; ``say`` is told once.  Submitting is as eager as the pool's."""

    def __init__(self, pool_map, say, what: str):
        self.pool_map, self.say, self.what = pool_map, say, what
        self.lost: str | None = None  # why the pool is gone, once it is

    def __call__(self, fn, *iterables):
        items = list(zip(*iterables))
        results = None
        if self.lost is None and self.pool_map is not map:
            try:
                results = self.pool_map(fn, *zip(*items)) if items else iter(())
            except BrokenProcessPool as exc:
                self.lose(exc)
        return self._results(fn, items, results)

    def _results(self, fn, items, results):
        done = 0
        if results is not None:
            try:
                for result in results:
                    done += 1
                    yield result
                return
            except BrokenProcessPool as exc:
                self.lose(exc)
        for args in items[done:]:
            yield fn(*args)

    def lose(self, exc) -> None:
        if self.lost is None:
            self.lost = f"{self.what} lost a process ({type(exc).__name__}: {exc})"
            self.say(f"{self.lost}: the rest of its work is done in this process")
