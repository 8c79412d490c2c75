"""bench/engine_prototypes.py: the claims a fused engine rests on (MuJoCo's step called
from a compiled loop leaves the state the Python bindings leave, bit for bit; messages
packed with orjson straight from arrays are the bytes ``MessageType.pack`` makes), the
Python-glue prototype's recording, and its flags."""

import runpy
from pathlib import Path

import numpy as np
import orjson
import pytest

from services.recordings.reader import read_episode
from services.runtime.messages import FT_WRENCH, ROBOT_COMMAND, ROBOT_CONTACT, ROBOT_STATE

ROOT = Path(__file__).resolve().parents[2]
PROTOTYPES = runpy.run_path(str(ROOT / "bench" / "engine_prototypes.py"))


def test_mujoco_step_from_a_numba_loop_leaves_the_state_python_leaves():
    numba_us, python_us, same = PROTOTYPES["compiled_steps"](200)
    assert same
    assert numba_us > 0 and python_us > 0


@pytest.mark.parametrize("episodes", ["0", "a,b", ""])
def test_a_bad_episodes_flag_is_refused_in_one_line(episodes, capsys):
    with pytest.raises(SystemExit) as exc:
        PROTOTYPES["main"](["--episodes", episodes])
    assert exc.value.code == 2
    assert "--episodes: comma-separated integers >= 1" in capsys.readouterr().err


def test_messages_packed_straight_from_arrays_are_the_bytes_pack_makes_from_lists():
    """What lets fused cycles skip the lists: orjson's numpy serializer writes float64 arrays
    as it writes the same numbers as Python floats, for the four 1 kHz messages' array
    fields (a wide spread of magnitudes, signed zeros, whole numbers)."""
    rng = np.random.default_rng(11)
    for k in range(300):
        scale = 10.0 ** rng.integers(-300, 300)
        for mtype in (ROBOT_STATE, ROBOT_CONTACT, FT_WRENCH, ROBOT_COMMAND):
            values, arrays = {}, {}
            for f in mtype.fields:
                if f.type.startswith("float[") and f.length:
                    a = rng.normal(size=f.length) * scale
                    a[k % f.length] = (0.0, -0.0, 1.0, 1e16)[k % 4]
                    values[f.name], arrays[f.name] = a.tolist(), a
                else:
                    v = {"int": 1, "float": 0.5, "bool": False, "str": "", "str[]": ["plate_left"]}.get(f.type, [1] * 6)
                    values[f.name] = arrays[f.name] = v
            payload, _ = mtype.pack(**values)
            assert orjson.dumps(arrays, option=orjson.OPT_SERIALIZE_NUMPY) == payload, (mtype.name, k)


def test_the_python_glue_prototype_records_four_messages_a_cycle_that_decode(tmp_path):
    us = PROTOTYPES["python_glue_cycle"](50, tmp_path)
    assert us > 0
    recordings = sorted(tmp_path.glob("glue_*.mcap"))
    assert recordings
    episode = read_episode(recordings[-1])
    types = {t.channel: t for t in (ROBOT_STATE, ROBOT_CONTACT, FT_WRENCH, ROBOT_COMMAND)}
    counts = {}
    for m in episode.messages:
        types[m.topic].decode(m.payload)  # raises MessageError if a field is wrong
        counts[m.topic] = counts.get(m.topic, 0) + 1
    assert set(counts) == set(types) and len(set(counts.values())) == 1 and min(counts.values()) >= 650
