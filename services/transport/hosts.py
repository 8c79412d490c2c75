"""Hosts on one machine: the run's services split across Linux network namespaces.

A lab cell is several computers: the KRC and the F/T sensor box, a real-time PC
with the estimator and the commander, a logging PC.  Here each *host* is a
network namespace of its own, with its own address, joined to the machine by a
veth pair on one bridge; the runner stays in the root namespace as the run's
Zenoh router on the bridge's address, and every service is a client of it (peers
listening on loopback cannot reach one another across namespaces).  What crosses
between hosts crosses a real network stack, and a host can be cut off
(``cut``: its link goes down) while its processes go on.

Layout::

    root namespace: bridge etar-br0, 10.231.0.1/24   (the runner: the Zenoh router)
    etar-h1 ... etar-hN: eth0 10.231.0.(10+i)/24, lo up, default route via .1
    veth etar-hI-r (root side, on the bridge) <-> eth0 (in etar-hI)

Needs root (CAP_NET_ADMIN) and iproute2's ``ip``.  One set of hosts per machine
at a time: ``up`` refuses while another run's namespaces still hold processes,
and clears what a crashed run left behind otherwise.  ``down`` is idempotent.

A cut host is noticed within the Zenoh lease the sessions use here
(``LEASE_MS``, on the router and on every client: each side keeps the other's).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from dataclasses import dataclass

PREFIX = "etar"
BRIDGE = f"{PREFIX}-br0"
NETWORK = "10.231.0"
ROUTER_ADDRESS = f"{NETWORK}.1"
# how long a silent link lives: the default 10 s would let a cut host go unnoticed that long
LEASE_MS = 1000
# Zenoh settings of every session of a run on hosts (router and clients): the lease, and
# how long a message sent with congestion control BLOCK may wait for a full queue before
# the link is closed (default 5 s: the router forwarding to a cut host stalled the robot's
# traffic that long, and the runner's 'stop' went unanswered)
ZENOH_CFG = (("transport/link/tx/lease", str(LEASE_MS)),
             ("transport/link/tx/queue/congestion_control/block/wait_before_close", str(LEASE_MS * 1000)))
MAX_HOSTS = 20
_NAMESPACE = re.compile(rf"^{PREFIX}-h\d+$")
_LINK = re.compile(rf"^{PREFIX}-(h\d+-[rn]|br0)$")


class HostsError(RuntimeError):
    """The hosts cannot be made (no root, no ip, another run's hosts in use)."""


@dataclass(frozen=True)
class Host:
    name: str  # h1, h2, ...
    roles: tuple
    index: int

    @property
    def namespace(self) -> str:
        return f"{PREFIX}-{self.name}"

    @property
    def address(self) -> str:
        return f"{NETWORK}.{10 + self.index}"

    @property
    def link(self) -> str:
        """The root namespace's end of its veth pair: down, the host is cut off."""
        return f"{PREFIX}-{self.name}-r"

    def describe(self) -> str:
        return f"host {self.name} ({self.address})"


def parse_layout(text: str, known_roles) -> tuple:
    """'robot,ft_sensor:phase_estimator,impedance_commander:recorder,teacher' -> hosts h1, h2, h3
    holding those roles.  Every role of the run must be on exactly one host."""
    groups = [tuple(r.strip() for r in g.split(",") if r.strip()) for g in text.split(":")]
    if not groups or any(not g for g in groups):
        raise ValueError(f"--hosts {text!r}: expected roles by host, e.g. robot,ft_sensor:phase_estimator,"
                         "impedance_commander:recorder,teacher")
    if len(groups) > MAX_HOSTS:
        raise ValueError(f"--hosts {text!r}: at most {MAX_HOSTS} hosts")
    seen = [r for g in groups for r in g]
    unknown = sorted(set(seen) - set(known_roles))
    if unknown:
        raise ValueError(f"--hosts {text!r}: {', '.join(unknown)} not a role of this run "
                         f"(its roles: {', '.join(known_roles)})")
    twice = sorted({r for r in seen if seen.count(r) > 1})
    if twice:
        raise ValueError(f"--hosts {text!r}: {', '.join(twice)} on more than one host")
    missing = [r for r in known_roles if r not in seen]
    if missing:
        raise ValueError(f"--hosts {text!r}: no host for {', '.join(missing)}")
    return tuple(Host(f"h{i}", g, i) for i, g in enumerate(groups, 1))


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run(["ip", *args], capture_output=True, text=True)
    if check and done.returncode != 0:
        raise HostsError(f"ip {' '.join(args)}: {done.stderr.strip()}")
    return done


def _namespaces() -> list[str]:
    out = _ip("netns", "list", check=False).stdout
    return [line.split()[0] for line in out.splitlines() if line.split() and _NAMESPACE.match(line.split()[0])]


def _links() -> list[str]:
    out = _ip("-o", "link", "show", check=False).stdout
    names = [line.split(": ")[1].split("@")[0] for line in out.splitlines() if ": " in line]
    return [n for n in names if _LINK.match(n)]


class Hosts:
    def __init__(self, hosts: tuple):
        self.hosts = tuple(hosts)
        self._by_role = {role: h for h in self.hosts for role in h.roles}
        self.made = False

    def host_of(self, role: str) -> Host | None:
        return self._by_role.get(role)

    def command_prefix(self, role: str) -> list[str]:
        """What runs a role's process inside its host."""
        return ["ip", "netns", "exec", self._by_role[role].namespace]

    def up(self) -> None:
        if os.geteuid() != 0 or shutil.which("ip") is None:
            raise HostsError("hosts in network namespaces need root and iproute2's ip")
        busy = [ns for ns in _namespaces() if _ip("netns", "pids", ns, check=False).stdout.strip()]
        if busy:
            raise HostsError(f"the namespaces {', '.join(busy)} hold processes: another run's hosts are in use")
        down()  # what a crashed run left
        try:
            _ip("link", "add", BRIDGE, "type", "bridge")
            _ip("addr", "add", f"{ROUTER_ADDRESS}/24", "dev", BRIDGE)
            _ip("link", "set", BRIDGE, "up")
            for h in self.hosts:
                ns, inner = h.namespace, f"{PREFIX}-{h.name}-n"
                _ip("netns", "add", ns)
                _ip("link", "add", h.link, "type", "veth", "peer", "name", inner)
                _ip("link", "set", inner, "netns", ns)
                _ip("-n", ns, "link", "set", inner, "name", "eth0")
                _ip("-n", ns, "addr", "add", f"{h.address}/24", "dev", "eth0")
                _ip("-n", ns, "link", "set", "lo", "up")  # a new namespace's loopback is down
                _ip("-n", ns, "link", "set", "eth0", "up")
                _ip("-n", ns, "route", "add", "default", "via", ROUTER_ADDRESS)
                _ip("link", "set", h.link, "master", BRIDGE)
                _ip("link", "set", h.link, "up")
        except BaseException:
            down()
            raise
        self.made = True

    def cut(self, name: str) -> Host:
        """Take host ``name``'s link down: its processes go on, cut off from the run."""
        host = next(h for h in self.hosts if h.name == name)
        _ip("link", "set", host.link, "down")
        return host

    def down(self) -> None:
        if self.made:
            down()
            self.made = False


def down() -> None:
    """Remove every namespace and link of the layout (idempotent)."""
    for ns in _namespaces():
        # a process left inside keeps the namespace alive after its name is gone
        for pid in _ip("netns", "pids", ns, check=False).stdout.split():
            try:
                os.kill(int(pid), 9)
            except (ProcessLookupError, ValueError):
                pass
        _ip("netns", "del", ns, check=False)
    for link in _links():
        _ip("link", "del", link, check=False)
