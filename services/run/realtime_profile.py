"""The realtime profile: what the runner asks of the machine for a run on the 1 kHz clock.

Three parts, each applied where the machine permits it and reported either way:

- ``fifo``: SCHED_FIFO for the FRI chain at ordered priorities (``services.runtime.roles``): the
  robot above whoever answers its cycles (the commander in a reproduction, the
  teacher in a demonstration; never both at once), the sensor and the estimator
  below.  The recorder stays an ordinary process: it needs every message, not each
  one at once.  All at one priority starve one another on two cores (measured:
  97 % missed deadlines).
- ``isolate``: the robot alone on the last CPU, every other service on the others
  (needs two CPUs or more).
- ``poll``: /dev/cpu_dma_latency held at 0 for the run, as cyclictest does: idle CPUs
  poll instead of halting (on a virtual machine a halted vCPU took a few hundred
  microseconds to wake for a message).

``auto`` (the default with ``--clock realtime``) asks for all three, ``none`` for
nothing, or a comma list of parts (``fifo,isolate``).  ``probe`` finds out what
will be granted before any service starts, so the run says it in one line.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field

from services.runtime.roles import FIFO_CHAIN

PARTS = ("fifo", "isolate", "poll")
CPU_LATENCY_DEVICE = "/dev/cpu_dma_latency"
# what a refused part costs, measured on this project's 2-CPU machine (docs/realtime.md)
COST = {"fifo": "the FRI chain shares the CPUs with everything else: expect most cycles missed",
        "isolate": "the robot shares a CPU with the other services: expect loop deadline misses",
        "poll": "idle CPUs halt: each message waits for a vCPU to wake (hundreds of us)"}


def parse_profile(text: str) -> frozenset:
    """``auto`` | ``none`` | comma list of ``PARTS``; ValueError naming the bad value."""
    value = str(text).strip().lower()
    if value == "auto":
        return frozenset(PARTS)
    if value in ("none", ""):
        return frozenset()
    parts = [p.strip() for p in value.split(",") if p.strip()]
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        raise ValueError(f"realtime profile {text!r}: unknown part {unknown[0]!r} "
                         f"(auto, none, or a comma list of {', '.join(PARTS)})")
    return frozenset(parts)


@dataclass
class Grant:
    """What a profile asked for, what was granted and why the rest was refused."""

    requested: frozenset
    granted: set = field(default_factory=set)
    refused: dict = field(default_factory=dict)  # part -> reason
    _qos_fd: int | None = None

    def to_dict(self) -> dict:
        return {"requested": sorted(self.requested), "granted": sorted(self.granted), "refused": dict(self.refused)}

    def warning(self) -> str | None:
        """One line on what the refused parts will cost, or None."""
        if not self.refused:
            return None
        return "realtime profile: " + "; ".join(f"{p} refused ({why}): {COST[p]}" for p, why in self.refused.items())

    def release(self) -> None:
        if self._qos_fd is not None:
            os.close(self._qos_fd)  # the PM QoS request ends with the file
            self._qos_fd = None


def _fifo_permitted() -> str | None:
    """None if this process may use SCHED_FIFO (tried and undone), else why not."""
    if not hasattr(os, "sched_setscheduler"):
        return "not supported on this system"
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        os.sched_setscheduler(0, before[0], before[1])
        return None
    except PermissionError:
        return "not permitted (needs CAP_SYS_NICE or an RLIMIT_RTPRIO > 0)"
    except OSError as exc:
        return f"{exc.strerror or exc}"


def probe(parts: frozenset) -> Grant:
    """Try each requested part; ``poll`` is taken at once and held until ``release``."""
    grant = Grant(frozenset(parts))
    if "fifo" in parts:
        why = _fifo_permitted()
        if why is None:
            grant.granted.add("fifo")
        else:
            grant.refused["fifo"] = why
    if "isolate" in parts:
        cpus = len(os.sched_getaffinity(0))
        if cpus >= 2:
            grant.granted.add("isolate")
        else:
            grant.refused["isolate"] = f"this process may use {cpus} CPU"
    if "poll" in parts:
        try:
            fd = os.open(CPU_LATENCY_DEVICE, os.O_WRONLY)
            os.write(fd, struct.pack("i", 0))
            grant._qos_fd = fd
            grant.granted.add("poll")
        except OSError as exc:
            grant.refused["poll"] = f"{CPU_LATENCY_DEVICE}: {exc.strerror or exc}"
    return grant


# with isolate: who gets the robot's CPU.  The sensor there too made it worse (measured on
# 2 CPUs: FRI answered in time 57 % instead of 99 %, the sensor as far behind)
ROBOT_CPU_ROLES = ("robot",)


def placement(role: str, grant: Grant, *, sched_fifo: bool = False, fifo_priorities=(),
              isolate_robot: bool = False) -> tuple:
    """(SCHED_FIFO priority or None, CPUs or ()) of ``role``'s process.  ``sched_fifo``: the
    run's own priorities (``fifo_priorities``) whatever the profile; ``isolate_robot``: the
    robot on the last CPU whatever the profile."""
    if sched_fifo:
        priority = dict(fifo_priorities).get(role)
    else:
        priority = dict(FIFO_CHAIN).get(role) if "fifo" in grant.granted else None
    cpus = os.sched_getaffinity(0)
    if (isolate_robot or "isolate" in grant.granted) and len(cpus) >= 2:
        last = max(cpus)
        return priority, ((last,) if role in ROBOT_CPU_ROLES else tuple(sorted(cpus - {last})))
    return priority, ()
