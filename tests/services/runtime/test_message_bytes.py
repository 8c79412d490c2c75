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
