"""bench/engine_prototypes.py: the claim a fused engine rests on (MuJoCo's step called
from a compiled loop leaves the state the Python bindings leave, bit for bit), and its
flags."""

import runpy
from pathlib import Path

import pytest

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
