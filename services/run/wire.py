"""``etar-bench run --wire udp``: the run's own nodes over the lab's protocols.

The KRC speaks FRI 1.0 over UDP to the commander, its one remote (``--fri-listen``),
which passes each measurement on to the rest of the run; the sensor is a Net F/T box
whose RDT stream the estimator reads (``--netft``).  Everything on loopback, on ports
found free when the run starts.  The flags each role gets come from here.
"""

from __future__ import annotations

import socket

from services.transport.launch import free_port


def udp_wiring() -> dict[str, tuple]:
    """role -> the flags that put it on the lab's protocols (free loopback ports: a port
    taken between here and the service's start makes that service fail to start, saying so)."""
    fri = free_port(socket.SOCK_DGRAM)
    rdt, http = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
    return {
        # the wire itself is not recorded: recorded and reported as over Zenoh (serve records it)
        "robot": ("--wire", "udp", "--krl", "testbench", "--fri-remote", f"127.0.0.1:{fri}", "--no-wire-topic"),
        "impedance_commander": ("--fri-listen", f"127.0.0.1:{fri}"),
        "ft_sensor": ("--netft", "127.0.0.1", "--netft-rdt-port", str(rdt), "--netft-http-port", str(http),
                      "--netft-calibration-port", "0", "--no-netft-topic"),
        "phase_estimator": ("--netft", f"127.0.0.1:{rdt}", "--netft-http-port", str(http)),
    }
