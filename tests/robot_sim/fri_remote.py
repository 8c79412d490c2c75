"""A small FRI 1.0 remote for the tests, written from WIRE.md as a lab program would be.

It binds its UDP port, answers every measurement datagram to wherever it came from
(``reflSeqCount`` = the measurement's ``sendSeqCount``) and drives the KRL program through
one of the public conventions.  What it commands comes from ``plan(m, rec, state)``, a
function of the decoded measurement; what it saw is kept for the test to read.
Independent of the KRC side's code except for the datagram layouts (robot_sim.wire.fri_datagrams).
"""

from __future__ import annotations

import os
import socket
import threading

import numpy as np

from robot_sim.wire.fri_datagrams import (COMMAND_ID, COMMAND_SIZE, CommandFlags, FriWireError,
                                          decode_measurement, new_command)

# KRL indices (1-based, as KRL counts) of each convention
FRILIBRARY = dict(strategy=15, request=16, state=16, close_value=15, start=10, stop=20)
LWR_HW = dict(strategy=1, request=2, state=2, start=1, stop=0)


class Remote:
    """The remote's side.  ``krl``: 'frilibrary' or 'lwr_hw'; ``strategy`` (10 joint
    position, 20 Cartesian impedance, 30 joint impedance, 90 torque).  Set
    :attr:`request` to 'start', 'stop', 'close' or None; :attr:`command` says what to
    send in command mode: a function (decoded measurement record) -> (flags, dict of
    cmd fields) or None to mirror the measured pose."""

    def __init__(self, krl: str = "frilibrary", strategy: int = 20, port: int = 0):
        self.conv = FRILIBRARY if krl == "frilibrary" else LWR_HW
        self.krl = krl
        self.strategy = strategy
        self.request = None
        self.command = None
        self.stiffness = np.array([2000.0, 2000.0, 2000.0, 150.0, 150.0, 150.0])  # x y z A B C
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.received = 0
        self.wrong = 0
        self.last = None  # the newest decoded measurement
        self.states: list[tuple[int, int]] = []  # (intf.state, $FRI_TO_INT[state]) on every change
        self._send_seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.sock.close()

    def to_int(self, index: int) -> int:
        """$FRI_TO_INT[index] of the newest measurement."""
        return int(self.last["krl"]["intData"][index - 1])

    @property
    def krl_state(self) -> int:
        return self.to_int(self.conv["state"])

    def _run(self):
        # a lab's remote runs its FRI thread at a realtime priority (the Stanford library asks
        # for SCHED_FIFO 60): without it, this thread waits behind the test's others now and
        # then for longer than a cycle, and FRI never sees the 600 clean cycles command mode needs
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(60))
        except (PermissionError, OSError, AttributeError):
            pass
        buf = bytearray(2048)
        while not self._stop.is_set():
            try:
                n, source = self.sock.recvfrom_into(buf)
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                m = decode_measurement(memoryview(buf)[:n])
            except FriWireError:
                self.wrong += 1
                continue
            self.received += 1
            self.last = m
            key = (int(m["intf"]["state"]), int(m["krl"]["intData"][self.conv["state"] - 1]))
            if not self.states or self.states[-1] != key:
                self.states.append(key)
            self.sock.sendto(self._answer(m), source)

    def _answer(self, m) -> bytes:
        c = new_command()
        self._send_seq = (self._send_seq + 1) & 0xFFFF
        c["head"]["sendSeqCount"] = self._send_seq
        c["head"]["reflSeqCount"] = m["head"]["sendSeqCount"]
        c["head"]["packetSize"] = COMMAND_SIZE
        c["head"]["datagramId"] = COMMAND_ID
        ints = c["krl"]["intData"]
        ints[self.conv["strategy"] - 1] = self.strategy
        if self.request == "start":
            ints[self.conv["request"] - 1] = self.conv["start"]
        elif self.request == "stop":
            ints[self.conv["request"] - 1] = self.conv["stop"]
        elif self.request == "close":
            ints[self.conv["request"] - 1] = int(m["krl"]["intData"][self.conv["close_value"] - 1])
        cmd = c["cmd"]
        # mirror the KRC's commanded values, as a remote does in monitor mode
        cmd["cartPos"] = m["data"]["cmdCartPos"]
        cmd["jntPos"] = m["data"]["cmdJntPos"]
        cmd["cartStiffness"] = self.stiffness
        cmd["cartDamping"] = 0.7
        cmd["jntStiffness"] = 1000.0
        cmd["jntDamping"] = 0.7
        flags = {10: CommandFlags.POSITION, 30: CommandFlags.JNT_IMP}.get(self.strategy, CommandFlags.CART_IMP)
        if self.command is not None and int(m["intf"]["state"]) == 2:
            flags, fields = self.command(m)
            for name, value in fields.items():
                cmd[name] = value
        cmd["cmdFlags"] = int(flags)
        return c.tobytes()
