"""The remote's end of FRI 1.0 over UDP, for the testbench's commander (``--fri-listen``).

A socket bound where the KRC sends its measurements, read by a thread of its own: each
916-byte datagram becomes the ``robot/state`` message it stands for (the header's 16-bit
counter unwrapped to the cycle's number, the KRC's time rounded to its cycle, the
episode and gravity compensation from the testbench's KRL channels, the KRC's error as
``safety``) and is handed to ``on_measurement(msg, packed, recv_ns)``; :meth:`answer`,
called from there, sends the 376-byte command to the address the measurement came from.
A datagram that is not a measurement is counted (``garbage``) and dropped.
"""

from __future__ import annotations

import select
import socket
import threading
from collections.abc import Callable

from robot_sim.cycle import FRI_CYCLE_NS, FRI_RATE_HZ
from robot_sim.krc.krl import TB_ESTIMATE_SEQ, TB_GOAL_REACHED, TB_HOLD, TB_HOLDS, KrlChannels
from robot_sim.krc.packets import fri_order
from robot_sim.wire.fri_datagrams import (CommandFlags, FriWireError, counter16, decode_measurement, new_command,
                                          unwrap, write_krl)
from services.runtime.fri_messages import state_from_datagram

class FriRemoteSocket:
    """The remote's socket and its reading thread (the module docstring)."""

    def __init__(self, bind: tuple[str, int], on_measurement: Callable, clock: Callable[[], int]):
        self.on_measurement = on_measurement
        self.clock = clock
        self.received = self.garbage = self.answered = self.send_errors = 0
        self.last_error = ""
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind(bind)
        except OSError as exc:
            self._sock.close()
            raise OSError(exc.errno, f"--fri-listen {bind[0]}:{bind[1]}: {exc.strerror or exc}") from None
        self._seq = None  # the last measurement's cycle
        self._source = None  # where it came from: the answer goes there
        self._out = new_command()
        self._out["cmd"]["cmdFlags"] = int(CommandFlags.CART_IMP)
        self._krl = KrlChannels()
        self._sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fri-remote", daemon=True)
        self._thread.start()

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    def status(self) -> dict:
        return {"address": list(self.address), "received": self.received, "garbage": self.garbage,
                "answered": self.answered, "send_errors": self.send_errors, "last_error": self.last_error}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close()

    def _run(self) -> None:
        buf = bytearray(2048)
        view = memoryview(buf)
        while not self._stop.is_set():
            ready, _, _ = select.select([self._sock], [], [], 0.1)
            if not ready:
                continue
            try:
                n, source = self._sock.recvfrom_into(buf)
            except OSError:
                continue
            recv_ns = self.clock()
            self.received += 1
            try:
                rec = decode_measurement(view[:n])
            except FriWireError as exc:
                self.garbage += 1
                self.last_error = str(exc)
                continue
            self._source = source
            msg, packed = self._state(rec, recv_ns)
            self.on_measurement(msg, packed, recv_ns)

    def _state(self, rec, recv_ns: int):
        cycle = round(float(rec["intf"]["timestamp"]) * FRI_RATE_HZ)  # float32 seconds: exact to the cycle for 70 min
        near = cycle + 1 if self._seq is None else self._seq + 1  # the KRC's cycle k is measurement k + 1
        seq = self._seq = unwrap(int(rec["head"]["sendSeqCount"]), near)
        refl = int(rec["head"]["reflSeqCount"])
        packed = state_from_datagram(rec, seq=seq, stamp_ns=cycle * FRI_CYCLE_NS,
                                     reflected_seq=unwrap(refl, seq) if refl else -1, sent_ns=recv_ns)
        return packed[1], packed

    def answer(self, state: dict, cart_pos, cart_stiffness, cart_damping, add_tcp_ft, *, goal_reached: bool,
               hold: str, estimate_seq: int) -> bool:
        """The command answering measurement ``state`` (Cartesian impedance; stiffness and
        damping in x y z rx ry rz order, the wrench in FRI's), with the testbench's KRL values."""
        out = self._out
        self._sent += 1
        out["head"]["sendSeqCount"] = counter16(self._sent)
        out["head"]["reflSeqCount"] = counter16(state["seq"])
        krl = self._krl
        krl.set_flag(TB_GOAL_REACHED, goal_reached)
        krl.ints[TB_HOLD - 1] = TB_HOLDS.index(hold) if hold in TB_HOLDS else TB_HOLDS.index("other")
        krl.ints[TB_ESTIMATE_SEQ - 1] = estimate_seq
        write_krl(out, krl)
        cmd = out["cmd"]
        cmd["cartPos"] = cart_pos
        cmd["cartStiffness"] = fri_order(cart_stiffness)
        cmd["cartDamping"] = fri_order(cart_damping)
        cmd["addTcpFT"] = add_tcp_ft
        try:
            self._sock.sendto(out.tobytes(), self._source)
        except (OSError, TypeError) as exc:
            self.send_errors += 1
            self.last_error = str(exc)
            return False
        self.answered += 1
        return True
