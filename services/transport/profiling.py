"""Opt-in cProfile of a whole service process, for finding its hot spots.

    ETAR_PROFILE=/tmp/prof etar-bench run scenarios/smoke.yaml --clock realtime

With ``ETAR_PROFILE`` set, every service profiles its main thread and every
Zenoh callback, and writes ``<dir>/<service>-<pid>.prof`` (pstats format, all
threads merged) when it stops:

    python -m pstats /tmp/prof/robot-1234.prof

cProfile hooks only the thread that enables it, and Zenoh calls back on
threads Python did not start (``threading.setprofile`` never reaches them), so
each callback thread gets its own profiler, switched on around each call.
Profiling slows Python code by about 2x: use it to rank hot spots, not to time
them.
"""

from __future__ import annotations

import cProfile
import os
import pstats
import threading
from pathlib import Path

ENV = "ETAR_PROFILE"


class ProcessProfile:
    def __init__(self, name: str, directory: str | None = None):
        self.directory = directory if directory is not None else os.environ.get(ENV) or None
        self.name = name
        self._local = threading.local()
        self._profiles: list[cProfile.Profile] = []
        self._lock = threading.Lock()
        self._main = None

    @property
    def enabled(self) -> bool:
        return self.directory is not None

    def start(self) -> None:
        if self.enabled:
            self._main = cProfile.Profile()
            self._main.enable()

    def _profile(self) -> cProfile.Profile:
        p = getattr(self._local, "profile", None)
        if p is None:
            p = self._local.profile = cProfile.Profile()
            with self._lock:
                self._profiles.append(p)
        return p

    def wrap(self, fn):
        """``fn`` itself when profiling is off; else fn profiled on whatever thread calls it."""
        if not self.enabled:
            return fn

        def profiled(*args):
            p = self._profile()
            p.enable()
            try:
                return fn(*args)
            finally:
                p.disable()

        return profiled

    def stop(self) -> Path | None:
        if not self.enabled:
            return None
        if self._main is not None:
            self._main.disable()
        profiles = ([self._main] if self._main is not None else []) + list(self._profiles)
        profiles = [p for p in profiles if p.getstats()]
        if not profiles:
            return None
        stats = pstats.Stats(profiles[0])
        for p in profiles[1:]:
            stats.add(p)
        path = Path(self.directory) / f"{self.name}-{os.getpid()}.prof"
        path.parent.mkdir(parents=True, exist_ok=True)
        stats.dump_stats(path)
        return path
