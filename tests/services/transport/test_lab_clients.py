"""The run's own ends of the lab's protocols (``etar-bench run --wire udp``): the
commander's FRI 1.0 remote socket and the estimator's Net F/T client, each against the
other side built from the wire formats, and against garbage from a foreign peer."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np

from robot_sim.ati.sensor import AtiConfig, AtiSensor
from robot_sim.krc.packets import ControlMode, FriQuality, FriState, MeasurementPacket, fri_order
from robot_sim.krc.krl import (KrlChannels, TB_EPISODE, TB_ESTIMATE_SEQ, TB_GOAL_REACHED,
                               TB_GRAVITY_COMPENSATION, TB_HOLD, TB_HOLDS)
from robot_sim.wire.fri_datagrams import decode_command, encode_measurement, read_krl
from robot_sim.wire.netft import NetFtBox
from services.transport.lab.fri_remote import FriRemoteSocket
from services.transport.lab.netft_client import NetFtStream

POSE = np.array([1.0, 0, 0, 0.5, 0, -1.0, 0, 0.1, 0, 0, -1.0, 0.3])


def wait_for(predicate, seconds=5.0):
    end = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.005)


def measurement(seq: int) -> MeasurementPacket:
    return MeasurementPacket(seq, seq - 1, (seq - 1) * 1_000_000, FriState.CMD, FriQuality.PERFECT,
                             ControlMode.CART_IMP, np.linspace(-0.3, 0.3, 7), POSE.copy(),
                             np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3]), 1.0, 1e-4, 1e-5, 0.0)


def test_the_remote_socket_passes_measurements_on_and_answers_them():
    got = []
    remote = FriRemoteSocket(("127.0.0.1", 0), lambda msg, packed, recv: got.append((msg, packed)), time.monotonic_ns)
    krc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    krc.bind(("127.0.0.1", 0))
    krc.settimeout(2.0)
    try:
        krl = KrlChannels()
        krl.ints[TB_EPISODE - 1] = 4
        krl.set_flag(TB_GRAVITY_COMPENSATION, False)
        seq = 70_000  # past the 16-bit counter's wrap: the cycle comes back whole from the KRC's time
        krc.sendto(encode_measurement(measurement(seq), krl=krl), remote.address)
        krc.sendto(b"garbage from a foreign peer", remote.address)
        krc.sendto(encode_measurement(measurement(seq + 1), krl=krl)[:-1], remote.address)  # one byte short
        wait_for(lambda: remote.garbage == 2 and got)
        msg, packed = got[0]
        assert msg["seq"] == seq and msg["stamp_ns"] == (seq - 1) * 1_000_000 and msg["episode"] == 4
        assert msg["fri_state"] == FriState.CMD and not msg["gravity_compensation"]
        assert np.allclose(msg["msr_cart_pos"], POSE) and packed[0].startswith(b'{"seq":70000')
        remote.answer(msg, POSE, [0, 0, 0, 150, 100, 50], [0.7] * 6, [5.0, 0, 0, 0, 0, 0], goal_reached=True,
                      hold="wrench_saturated", estimate_seq=69_990)
        data, _ = krc.recvfrom(2048)
        cmd = decode_command(data)
        assert int(cmd["head"]["reflSeqCount"]) == seq & 0xFFFF
        assert np.allclose(fri_order(cmd["cmd"]["cartStiffness"]), [0, 0, 0, 150, 100, 50])
        frm = read_krl(cmd)
        assert frm.flag(TB_GOAL_REACHED) and TB_HOLDS[frm.ints[TB_HOLD - 1]] == "wrench_saturated"
        assert frm.ints[TB_ESTIMATE_SEQ - 1] == 69_990
        assert remote.status()["answered"] == 1
    finally:
        remote.close()
        krc.close()


def test_the_net_ft_client_reads_a_box_that_comes_up_after_it():
    """The estimator's client starts before the sensor's box (the services start together),
    then streams: each record as the ft/wrench message of its cycle, values in N and N m."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u, socket.socket() as t:
        u.bind(("127.0.0.1", 0))
        t.bind(("127.0.0.1", 0))
        rdt_port, http_port = u.getsockname()[1], t.getsockname()[1]
    got = []
    client = NetFtStream(("127.0.0.1", rdt_port), http_port, lambda msg, recv: got.append(msg), time.monotonic_ns)
    try:
        time.sleep(0.5)  # nobody there yet
        config = AtiConfig.mini45()
        sensor = AtiSensor(config, 2, clock_origin_ns=0)
        wrench = np.array([1.0, -2.0, 3.0, 0.1, -0.2, 0.3])
        with NetFtBox(config, rdt_port=rdt_port, http_port=http_port, calibration_port=None) as box:
            stop = threading.Event()
            records = {}

            def feed():
                k = 0
                while not stop.is_set():
                    rec = sensor.read(wrench, k * 1_000_000)
                    records[rec.ft_sequence] = rec
                    box.publish(rec)
                    k += 1
                    time.sleep(0.001)
            feeder = threading.Thread(target=feed, daemon=True)
            feeder.start()
            wait_for(lambda: len(got) > 200, 10.0)
            stop.set()
            feeder.join()
        status = client.status()
        assert status["calibrated"] and status["out_of_order"] == 0 and status["garbage"] == 0
        for msg in got[:200]:
            rec = records[msg["ft_sequence"]]
            # the sensor counts its samples from the cell's start: a record's cycle is its ft_sequence
            assert msg["seq"] == msg["ft_sequence"] and msg["stamp_ns"] == (msg["seq"] - 1) * 1_000_000
            assert msg["counts"] == rec.counts.tolist() and msg["status"] == 0
            assert np.allclose(msg["wrench"], rec.wrench(config), atol=1e-12)
    finally:
        client.close()


def test_a_stream_asked_for_again_is_not_out_of_order_behind_the_old_streams_last_records():
    """After a stall of RESTART_S the client asks for the stream again, which the box numbers
    from 1 again; records of the old stream still on their way arrive first.  Those are
    taken, the new stream's 1 is its beginning (not out of order); without a new request,
    a record behind the last one is out of order and dropped."""
    client = NetFtStream(("127.0.0.1", 9), 9, lambda msg, recv: None, time.monotonic_ns)
    client.close()  # no box: the records are handed to it as its socket would
    client.cpf, client.cpt = 1_000_000.0, 1_000_000.0

    def feed(*rdts):
        for rdt in rdts:
            client._take((rdt, rdt, 0, 0, 0, 0, 0, 0, 0), 0)

    client._asked_again = True  # what the client's own request sets
    feed(57, 58, 1, 2, 3)
    assert (client.records, client.out_of_order, client.lost) == (5, 0, 0)
    feed(5, 4)  # 4 lost, then late: no new stream was asked for
    assert (client.records, client.out_of_order, client.lost) == (6, 1, 1)
