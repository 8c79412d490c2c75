"""Key expressions: everything of a run lives under ``etar/<run_id>/``."""

from __future__ import annotations

import re

_RUN_ID = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


def check_run_id(run_id: str) -> str:
    if not _RUN_ID.match(run_id or ""):
        raise ValueError(f"run id {run_id!r}: use 1-64 letters, digits, '-' or '_' (it becomes a key expression)")
    return run_id


def prefix(run_id: str) -> str:
    return f"etar/{check_run_id(run_id)}"


def key(run_id: str, topic: str) -> str:
    return f"{prefix(run_id)}/{topic}"


def control(run_id: str, service: str) -> str:
    return key(run_id, f"{service}/control")


def alive(run_id: str, service: str) -> str:
    return key(run_id, f"alive/{service}")


def listening(run_id: str, service: str, episode: int | str) -> str:
    """The liveliness token a service declares once its subscriptions for ``episode`` are
    (services.transport.process.NodeInputs); ``"*"`` for any."""
    return key(run_id, f"listening/{service}/{episode}")
