"""A message's bytes written by a kernel from arrays (services.runtime.message_bytes): the
bytes and the dict ``pack`` gives, for every value a field can take."""

import numpy as np
import pytest

from services.runtime.message_bytes import MessageBytes
from services.runtime.messages import FT_WRENCH, ROBOT_CONTACT, ROBOT_STATE

pytestmark = pytest.mark.skipif(not MessageBytes.available, reason="the kernels' JSON writer is not built")


def fill(mb: MessageBytes, values: dict) -> None:
    for name, value in values.items():
        array, at, n = mb.slots[name]
        (mb.ints if array == "ints" else mb.floats)[at:at + n] = value


def random_values(rng, mtype) -> dict:
    values = {}
    for f in mtype.fields:
        n = f.length or 1
        if f.base == "int":
            v = rng.integers(-2**62, 2**62, size=n)
            if f.name == "counts":
                v = rng.integers(-2**31, 2**31, size=n)
        elif f.base == "bool":
            v = rng.integers(0, 2, size=n).astype(bool)
        else:
            v = rng.normal(size=n) * 10.0 ** rng.integers(-9, 18, size=n)
        values[f.name] = v.tolist() if "[" in f.type else v.tolist()[0]
    return values


@pytest.mark.parametrize("mtype, whole", [(FT_WRENCH, ("counts",)), (ROBOT_STATE, ())])
def test_the_bytes_and_the_dict_are_packs(mtype, whole):
    rng = np.random.default_rng(11)
    mb = MessageBytes(mtype, whole=whole)
    for _ in range(3000):
        values = random_values(rng, mtype)
        fill(mb, values)
        payload, message = mtype.pack(**values)
        assert mb.write() == payload
        assert mb.message() == message
        assert [type(v) for v in mb.message().values()] == [type(v) for v in message.values()]


def test_a_value_json_cannot_hold_is_left_to_pack_which_names_the_field():
    mb = MessageBytes(FT_WRENCH, whole=("counts",))
    values = random_values(np.random.default_rng(1), FT_WRENCH)
    values["wrench"][3] = float("nan")
    fill(mb, values)
    assert mb.write() is None
    with pytest.raises(ValueError, match="wrench"):
        FT_WRENCH.pack(**values)


def test_a_message_with_a_field_it_cannot_write_is_refused_when_made():
    with pytest.raises(ValueError, match="touching"):
        MessageBytes(ROBOT_CONTACT)


def test_the_sensor_over_a_bus_of_bytes_alone_publishes_the_bytes_it_publishes_in_memory():
    """Over Zenoh (a bus that carries no dict) the sensor samples and writes ft/wrench's bytes
    in one kernel call, without the dict; the same seed and clock give the same bytes as in
    memory: NaN gauges (one, then three in a row), loads past the range, a tare, and more
    samples than a block of drawn noise."""
    from services.nodes.ft_sensor import FtSensorConfig, FtSensorNode
    from services.runtime.bus import FakeClock

    class Bus:
        def __init__(self, carries_dicts):
            self.carries_dicts, self.sent = carries_dicts, []

        def publish(self, topic, payload, message=None):
            self.sent.append((topic, payload, message))

    rng = np.random.default_rng(5)
    contacts = [dict(seq=k, stamp_ns=k * 1_000_000, sent_ns=0, wrench=rng.normal(size=6).tolist(), episode=0)
                for k in range(1, 1300)]
    contacts[20]["wrench"][2] = float("nan")
    for k in (600, 601, 602):
        contacts[k]["wrench"][0] = float("nan")
    for k in range(700, 720):
        contacts[k]["wrench"][1] = 1e4  # past the Mini45's range: saturated, clipped
    buses = []
    for carries in (True, False):
        bus = Bus(carries)
        node = FtSensorNode(FtSensorConfig(seed=3), bus, FakeClock(7))
        for k, msg in enumerate(contacts):
            if k == 300:
                node.tare({"samples": 50})
            node.on_contact(msg, 0, b"")
        buses.append(bus)
    in_memory, bytes_only = buses
    assert [s[1] for s in in_memory.sent] == [s[1] for s in bytes_only.sent] and len(in_memory.sent) == 1299
    assert FT_WRENCH.decode(bytes_only.sent[710][1])["status"] != 0
    assert all(type(s[2]) is dict for s in in_memory.sent)
    assert all(type(s[2]) is tuple for s in bytes_only.sent)
    # the NaN reached the model, whose record says so in its status bits, the same both ways
    assert FT_WRENCH.decode(bytes_only.sent[20][1])["status"] != 0 == FT_WRENCH.decode(bytes_only.sent[19][1])["status"]
