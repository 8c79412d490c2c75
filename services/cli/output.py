"""What the command lines say besides their results: one line on stderr, at once."""

from __future__ import annotations

import sys


def say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)
