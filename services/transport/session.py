"""Zenoh session configuration shared by every service (one helper, as zenoh-python's examples do).

Embedded default: a peer on loopback, multicast scouting off, listening on its
own ``tcp/127.0.0.1:0`` and connecting to the endpoints given (the runner's):
Zenoh peers do not relay for one another, so every peer listens and gossip
links them directly (DESIGN.md).  ``--mode client --connect tcp/HOST:PORT``
joins a Zenoh router instead (docker-compose).  ``--cfg KEY:VALUE`` sets any
other Zenoh configuration key (a misspelt key is refused by Zenoh); the flags
themselves are parsed in ``services.cli.zenoh_flags``.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass

import zenoh


@dataclass(frozen=True)
class ZenohOptions:
    mode: str = "peer"
    connect: tuple = ()
    listen: tuple = ("tcp/127.0.0.1:0",)
    cfg: tuple = ()  # (key, json5 value) pairs

    def config(self) -> zenoh.Config:
        """The Zenoh configuration; a value Zenoh refuses raises ValueError naming the flag."""
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        for flag, key, values in (("--listen", "listen/endpoints", self.listen),
                                  ("--connect", "connect/endpoints", self.connect)):
            for value in values:  # one at a time: the error names the endpoint at fault
                _insert(conf, key, json.dumps([value]), f"{flag} {value}")
            if values:
                _insert(conf, key, json.dumps(list(values)), flag)
        for key, value in self.cfg:
            _insert(conf, key, value, f"--cfg {key}:{value}")
        return conf

    def to_args(self) -> list[str]:
        """The same options as command-line flags (for spawning a service)."""
        out = ["--mode", self.mode]
        for e in self.connect:
            out += ["--connect", e]
        for e in self.listen:
            out += ["--listen", e]
        for k, v in self.cfg:
            out += ["--cfg", f"{k}:{v}"]
        return out


def zenoh_reason(exc: Exception) -> str:
    """Zenoh's own words from one of its errors, without the Rust source locations."""
    text = str(exc)
    m = re.search(r'msg: "(.*?)(?: at /[^"]*)?"', text)
    if m:
        text = m.group(1)
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", text).strip()
    return re.sub(r'^Str\("(.*)"\)$', r"\1", text)


def _insert(conf: zenoh.Config, key: str, value: str, flag: str) -> None:
    try:
        conf.insert_json5(key, value)
    except zenoh.ZError as exc:
        raise ValueError(f"{flag}: {zenoh_reason(exc)}") from None


def open_session(options: ZenohOptions) -> zenoh.Session:
    return zenoh.open(options.config())
