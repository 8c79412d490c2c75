"""The report's decoding of the recordings, started while the run goes on.

The report decodes every recording once (``services.results.decoding``): on the valley in
one process, 7 s after the last reproduction, while during the reproductions one core of
two stepped the cell and the other had little to do.  ``ReportReads`` decodes each
recording in a process beside the run as soon as the recording is complete and what the
report takes from it is known (after the learn stage: the phase mapping its reproductions
are scored with, the figures' view), and hands the report what it decoded; the report
decodes only what is not there or whose reading has changed since (``decode_episodes``
compares them), so the report is the same either way.  Lockstep only: on the realtime
clock that work would take CPU the 1 kHz loop needs; not in a sweep, whose runs take the
CPUs already (``workers`` 1); not before the recordings are worth a process's start
(``PARALLEL_READ_BYTES``, as the report decides: a smoke's are not).  The same process
draws the figures that need no reproduction (the demonstrations', the learning's) while
the reproductions run (``start``): the valley's figures after its report 2.1 -> 0.5 s,
the same files byte for byte.  A process beside the run that is lost (killed) costs the
run nothing: its work not done is done in the run's process when the reads end
(``services.runtime.threads.FallbackMap``, as for the learn stage's pool).
"""

from __future__ import annotations

import contextlib

from services.results.decoding import PARALLEL_READ_BYTES, decode_episode, recordings_size
from services.runtime.threads import FallbackMap, process_map

WHAT = "the report's reader beside the run"


class ReportReads:
    """As a context manager: on a clean exit, what was started is waited for and kept in
    ``decoded`` ((reading, DecodedEpisode) pairs, for ``write_report``); on a failure the
    process is terminated with the run and the report decodes everything itself."""

    def __init__(self, wanted: bool, at_least: int = PARALLEL_READ_BYTES, say=print):
        """``at_least``: the bytes of recordings that make starting the process worth it;
        ``say``: told once if the process is lost."""
        self.wanted, self.at_least, self._say = wanted, at_least, say
        self.decoded: list = []
        self.ahead: dict = {}  # name -> the result of work done beside (``start``), once the reads end
        self._started: list = []  # (reading, the pool's iterator of its one result)
        self._ahead: list = []  # (name, the pool's iterator of its one result)
        self._stack = contextlib.ExitStack()
        self._map = None

    def catch_up(self, readings) -> None:
        """Start decoding every reading of ``readings`` (the report's, as of now) not started yet."""
        if not self._beside(readings):
            return
        for reading in readings:
            if not any(reading == started for started, _ in self._started):
                self._started.append((reading, self._map(decode_episode, [reading])))

    def start(self, name: str, fn, args: tuple, readings) -> bool:
        """Run ``fn(*args)`` in the process beside the run, after what it has been given to
        decode, when the recordings ``readings`` are worth that process; its result in
        ``ahead[name]`` once the reads end (none if it failed: the report's own work then
        does it).  Whether it was started."""
        if not self._beside(readings):
            return False
        self._ahead.append((name, self._map(_call, [(fn, args)])))
        return True

    def _beside(self, readings) -> bool:
        """Whether the process beside the run is there (started now, if wanted and worth it)."""
        if not self.wanted:
            return False
        if self._map is None:
            if recordings_size(readings) < self.at_least:
                return False
            self._map = FallbackMap(self._stack.enter_context(process_map(1, beside=True)), self._say, WHAT)
        return True

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        started, self._started = self._started, []
        ahead, self._ahead = self._ahead, []
        if exc_type is None:
            try:
                for reading, result in started:
                    try:
                        self.decoded.append((reading, next(result)))
                    except Exception:  # noqa: BLE001 - the report decodes it again and says what is wrong
                        pass
                for name, result in ahead:
                    try:
                        self.ahead[name] = next(result)
                    except Exception:  # noqa: BLE001 - the report's own work does it, and says what is wrong
                        pass
            except BaseException as waiting:  # Ctrl-C while waiting: the process goes with the run
                self._stack.__exit__(type(waiting), waiting, waiting.__traceback__)
                raise
        return self._stack.__exit__(exc_type, exc, tb)


def _call(job: tuple):
    fn, args = job
    return fn(*args)
