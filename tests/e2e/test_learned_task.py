"""A model made by ``etar learn`` from a run's recordings is a learned task a scenario
can reproduce (``model:``), the same as the runner's own learn stage makes."""

import json

import numpy as np
import pytest

from services.cli.etar import main as etar
from services.scenario import Scenario
from tests import support

# whole runs in one process (seconds each): the slow lane
pytestmark = [pytest.mark.slow]


def test_a_model_learned_by_etar_learn_is_reproduced_by_a_scenario(tmp_path):
    demo = tmp_path / "demo"
    smoke = support.scenario("smoke").described()
    # the smoke scenario's demonstrations alone
    only_demos = Scenario.from_dict(dict(smoke, stages=[s for s in smoke["stages"] if "demonstrate" in s]))
    report = support.run(only_demos, demo, transport="inproc")
    assert report["error"] is None and len(report["demonstrations"]) == 2

    recordings = sorted(str(p) for p in (demo / "recordings").glob("demonstration_*.mcap"))
    assert etar(["learn", *recordings, "--phases", "3", "--restarts", "2", "--max-iter", "60",
                 "--out", str(tmp_path / "learned" / "model.json")]) == 0
    meta = json.loads((tmp_path / "learned" / "model.json").read_text())["metadata"]
    assert len(meta["goal"]) == 3 and len(meta["impedance"]) == 3
    assert sorted(meta["phase_to_truth"].values()) == [0, 1, 2]  # matched on the recordings' true labels

    reproduce = Scenario.from_dict(dict(name="reproduce_learned", world="valley", seed=0,
                                        model=str(tmp_path / "learned" / "model.json"),
                                        stages=[s for s in smoke["stages"] if "reproduce" in s]))
    report = support.run(reproduce, tmp_path / "repro", transport="inproc")
    assert report["error"] is None, report["error"]
    (rp,) = report["reproductions"]
    assert rp["success"], rp["reason"]
    assert rp["phases"]["accuracy"] > 0.8


def _replayed_posteriors(task, recording, resolution):
    """The estimator's posteriors over a reproduction, replayed offline from the recorded
    robot states and wrenches it took, with the state rounded to ``resolution``."""
    from etar.features import force_vector, pose_of, state_vector
    from services.recordings.arrays import recording_arrays

    arrays = recording_arrays(recording)
    est, st, ft = arrays["/estimator/phase"], arrays["/robot/state"], arrays["/ft/wrench"]
    row_of = {int(s): i for i, s in enumerate(st["seq"])}
    wrench_of = {int(s): i for i, s in enumerate(ft["seq"])}
    filt = task.model.filter()
    R0, out = None, []
    for k, (seq, ft_seq) in enumerate(zip(est["input_seq"], est["ft_seq"])):
        cart = st["msr_cart_pos"][row_of[int(seq)]]
        R0 = pose_of(cart)[0] if R0 is None else R0
        s = state_vector(cart, task.state, R0, resolution)
        f = force_vector(ft["wrench"][wrench_of[int(ft_seq)]], cart, task.features)
        out.append(filt.anchor(s, f) if est["unconditioned"][k] else filt.update(s, f))
    return np.array(out), est["posterior"]


def test_a_coarser_state_is_what_the_learner_and_the_online_estimator_both_see(tmp_path):
    """``state_resolution`` rounds ETAR's state position to a grid in the learner and in the
    online estimator alike: the model file carries the pitch, and the estimates of a
    reproduction are the filter over the recorded states rounded to it (not unrounded)."""
    from etar.task import load_task

    coarse = support.scenario("smoke", {"state_resolution": 0.002})
    report = support.run(coarse, tmp_path / "coarse", transport="inproc")
    assert report["error"] is None, report["error"]
    task = load_task(tmp_path / "coarse" / "model.json")
    assert task.state_resolution == 0.002
    meta = json.loads((tmp_path / "coarse" / "model.json").read_text())["metadata"]
    assert meta["state_resolution"] == 0.002
    (recording,) = sorted((tmp_path / "coarse" / "recordings").glob("reproduction_*.mcap"))
    replayed, online = _replayed_posteriors(task, recording, 0.002)
    assert len(online) > 150
    np.testing.assert_allclose(replayed, online, atol=1e-9)
    unrounded, _ = _replayed_posteriors(task, recording, 0.0)
    assert np.abs(unrounded - online).max() > 1e-3

    # a stored model is reproduced only by a scenario that asks for the same state
    from services.run.preflight import preflight
    from services.scenario import ScenarioError

    smoke = support.scenario("smoke").described()
    reproduce = dict(name="coarse_model", world="valley", seed=0, model=str(tmp_path / "coarse" / "model.json"),
                     stages=[s for s in smoke["stages"] if "reproduce" in s])
    with pytest.raises(ScenarioError, match=r"model: .*rounded to 0.002 m, the scenario asks for 0 m"):
        preflight(Scenario.from_dict(reproduce))
    assert preflight(Scenario.from_dict(dict(reproduce, state_resolution=0.002))) is not None
