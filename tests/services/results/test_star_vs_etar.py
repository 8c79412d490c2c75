"""ETAR against STAR: the verdict on the thesis' claim, the sweep's rows per model, and the
scenario keys that ask for both models, on hand-made figures whose answer is known."""

import pytest

from services.results.compare import comparison_over_seeds, paired, verdict
from services.scenario.checks import ScenarioError
from services.scenario.loading import load_scenario
from services.run.sweep_table import by_model_rows
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def figures(**values):
    """{key: stat} from key=(mean, min, max, n)."""
    return {k: {"mean": v[0], "min": v[1], "max": v[2], "n": v[3]} for k, v in values.items()}


def claim(etar: dict, star: dict) -> str:
    return verdict({"ETAR": etar, "STAR": star})[-1]


CLEAR_ETAR = figures(filter_accuracy=(0.99, 0.985, 0.995, 3), filter_spurious_switches=(2, 1, 3, 3),
                     error_near_transitions=(1e-8, 0.9e-8, 1.1e-8, 3))
CLEAR_STAR = figures(filter_accuracy=(0.95, 0.94, 0.96, 3), filter_spurious_switches=(9, 8, 10, 3),
                     error_near_transitions=(5e-8, 4e-8, 6e-8, 3))


def test_the_claim_holds_when_etar_is_better_on_every_figure_by_more_than_the_spread():
    text = claim(CLEAR_ETAR, CLEAR_STAR)
    assert "HOLDS" in text and "Predictions worse at transitions: STAR." not in text
    assert text.endswith("Predictions worse at transitions: STAR")


def test_the_claim_fails_when_star_is_clearly_better_on_one_figure():
    text = claim(CLEAR_STAR, CLEAR_ETAR)
    assert "does NOT hold" in text
    lines = verdict({"ETAR": CLEAR_STAR, "STAR": CLEAR_ETAR})
    assert any(line.strip().startswith("online filter accuracy") and line.endswith("better: STAR") for line in lines)


def test_differences_inside_the_seed_spread_only_hold_in_direction_and_one_seed_cannot_judge():
    wide = figures(filter_accuracy=(0.97, 0.90, 0.99, 3), filter_spurious_switches=(5, 1, 20, 3),
                   error_near_transitions=(2e-8, 1e-8, 9e-8, 3))
    worse = figures(filter_accuracy=(0.96, 0.90, 0.99, 3), filter_spurious_switches=(6, 1, 20, 3),
                    error_near_transitions=(3e-8, 1e-8, 9e-8, 3))
    assert "holds in direction only" in claim(wide, worse)
    assert "is not decided here" in claim(worse, wide)
    one = {k: dict(v, n=1, min=v["mean"], max=v["mean"]) for k, v in CLEAR_ETAR.items()}
    other = {k: dict(v, n=1, min=v["mean"], max=v["mean"]) for k, v in CLEAR_STAR.items()}
    assert "cannot be judged from one seed (in direction it holds)" in claim(one, other)
    assert "cannot be judged from one seed (in direction it does not hold)" in claim(other, one)


def test_online_figures_count_for_accuracy_and_a_missing_figure_drops_the_claim():
    online_worse = dict(CLEAR_ETAR, **figures(online_phase_accuracy=(0.90, 0.89, 0.91, 3)))
    online_better = dict(CLEAR_STAR, **figures(online_phase_accuracy=(0.99, 0.98, 1.0, 3)))
    assert "does NOT hold" in claim(online_worse, online_better)
    no_switches = {k: v for k, v in CLEAR_ETAR.items() if k != "filter_spurious_switches"}
    assert not any("the thesis' claim" in line for line in verdict({"ETAR": no_switches, "STAR": CLEAR_STAR}))


def test_a_sweep_row_of_a_run_with_two_models_becomes_a_row_per_model_and_the_seeds_are_compared():
    rows = []
    for seed, (a, b) in enumerate([(0.99, 0.95), (0.98, 0.96)]):
        rows.append({"run": f"run{seed:03d}", "seed": seed, "error": None, "successes": 4, "reproductions": 4,
                     "online_phase_accuracy": (a + b) / 2, "by_model": {
                         "ETAR": {"filter_accuracy": a, "filter_spurious_switches": 2.0, "error_near_transitions": 1e-8,
                                  "success_rate": 1.0, "online_phase_accuracy": a, "mean_peak_contact_force_n": 20.0},
                         "STAR": {"filter_accuracy": b, "filter_spurious_switches": 7.0, "error_near_transitions": 3e-8,
                                  "success_rate": 0.5, "online_phase_accuracy": b, "mean_peak_contact_force_n": 25.0}}})
    rows.append({"run": "run002", "seed": 2, "error": "RuntimeError: boom"})
    out = by_model_rows(rows)
    assert [(r["run"], r.get("param model")) for r in out] == [("run000", "ETAR"), ("run000", "STAR"),
                                                                ("run001", "ETAR"), ("run001", "STAR"), ("run002", None)]
    assert out[1]["online_phase_accuracy"] == 0.95 and out[1]["peak_contact_force_n"] == 25.0
    assert out[1]["successes"] is None and "by_model" not in out[1]
    text = comparison_over_seeds(out)
    assert text[0].startswith("ETAR against STAR over 2 data seed(s) (0, 1)")
    assert any("HOLDS" in line for line in text if line.startswith("the thesis"))
    success = next(line for line in text if "reproductions reaching the goal" in line)
    assert "ETAR          1 (1..1)" in success and "STAR        0.5 (0.5..0.5)" in success
    assert comparison_over_seeds([{"run": "r", "seed": 0, "error": None}]) is None
    paired_lines = text[text.index("paired by data seed (the same demonstrations and starts for both models):") + 1:]
    accuracy = next(line for line in paired_lines if "online filter accuracy" in line)
    assert accuracy.endswith("ETAR better in 2 of 2 seeds, STAR in 0, equal in 0")
    switches = next(line for line in paired_lines if "spurious switches" in line)
    assert switches.endswith("ETAR better in 2 of 2 seeds, STAR in 0, equal in 0")  # fewer is better


def test_the_star_vs_etar_scenario_learns_both_models_and_reproduces_each_start_with_both():
    sc = load_scenario(ROOT / "scenarios" / "star_vs_etar.yaml")
    assert sc.learn_stage.transitions == ("effect", "state")
    assert sc.reproduce_stages[0].transitions == ("effect", "state")
    assert load_scenario(ROOT / "scenarios" / "valley.yaml").learn_stage.transitions == ("effect",)


@pytest.mark.parametrize("learn, path, message", [
    (["effect", "effect"], "stages[1].learn.transitions", "listed twice"),
    (["effect", "star"], "stages[1].learn.transitions[1]", "expected one of 'effect', 'state'"),
    ([], "stages[1].learn.transitions", "expected one of effect, state or a list"),
    # the reproduce stage asks for [effect, state]
    ("effect", "stages[2].reproduce.transitions", "the learn stage learns ['effect'], not ['state']"),
])
def test_bad_transition_lists_are_refused_naming_the_field(learn, path, message):
    with pytest.raises(ScenarioError) as err:
        load_scenario(ROOT / "scenarios" / "star_vs_etar.yaml").replace("learn.transitions", learn)
    assert path in str(err.value) and message in str(err.value) and "star_vs_etar.yaml" in str(err.value)


def test_paired_counts_which_model_was_better_in_each_seed():
    by_seed = {0: {"ETAR": {"filter_accuracy": 0.9, "mean_peak_contact_force_n": 20.0},
                   "STAR": {"filter_accuracy": 0.8, "mean_peak_contact_force_n": 25.0}},
               1: {"ETAR": {"filter_accuracy": 0.7, "mean_peak_contact_force_n": 20.0},
                   "STAR": {"filter_accuracy": 0.8, "mean_peak_contact_force_n": 20.0}},
               2: {"ETAR": {"filter_accuracy": 0.9}}}  # a seed with one model only does not count
    lines = paired(by_seed)
    assert len(lines) == 2
    assert lines[0].endswith("ETAR better in 1 of 2 seeds, STAR in 1, equal in 0")
    assert lines[1].endswith("ETAR better in 1 of 2 seeds, STAR in 0, equal in 1")  # less force is better


def test_a_sweep_over_a_parameter_compares_the_models_at_each_value_on_its_own():
    rows = []
    for noise, (a, b) in ((1, (0.99, 0.95)), (64, (0.90, 0.97))):
        for seed in (0, 1):
            for name, acc in (("ETAR", a), ("STAR", b)):
                rows.append({"run": f"n{noise}s{seed}", "param cell.sensor_noise": noise, "param model": name,
                             "seed": seed, "error": None, "filter_accuracy": acc + 0.001 * seed})
    text = comparison_over_seeds(rows)
    first, second = text.index("at cell.sensor_noise=1:"), text.index("at cell.sensor_noise=64:")
    low = next(line for line in text[first:second] if "online filter accuracy" in line)
    high = next(line for line in text[second:] if "online filter accuracy" in line)
    assert "better: ETAR" in low and "0.95" not in low.split("STAR")[0]
    assert "better: STAR" in high
    assert text[first + 1].startswith("ETAR against STAR over 2 data seed(s) (0, 1)")


def test_the_sweep_table_pairs_the_seeds_and_calls_a_difference_only_beyond_both_ranges(tmp_path):
    """bench/star_vs_etar_sweep.py on two hand-made sweep folders: the paired counts, the
    'beyond spread' column at each value, the baseline borrowed from the other sweep, the
    figure written; a folder that is not such a sweep is refused in one line."""
    import json
    import runpy

    def sweep(folder, param, values, figure, fixed=None):
        rows = [{"run": f"{v}-{seed}", f"param {param}": v, "param model": name, "seed": seed, "error": None,
                 "filter_accuracy": figure(v, seed, name)}
                for v in values for seed in (0, 1, 2) for name in ("ETAR", "STAR")]
        folder.mkdir()
        parameters = {"model": ["ETAR", "STAR"], param: values, **(fixed or {})}
        (folder / "sweep.json").write_text(json.dumps({"parameters": parameters}))
        (folder / "table.json").write_text(json.dumps(rows))
        return folder

    # noise 1: ETAR ahead by 0.05 with ranges of 0.02: beyond; noise 64: ETAR ahead in 2 of 3 seeds
    # by less than the range: no verdict
    noise = sweep(tmp_path / "noise", "cell.sensor_noise", [1, 64],
                  lambda v, seed, name: (0.95 + 0.01 * seed + (0.05 if name == "ETAR" else 0.0)) if v == 1
                  else [[0.90, 0.89], [0.93, 0.92], [0.90, 0.95]][seed][name == "STAR"])
    grid = sweep(tmp_path / "grid", "state_resolution", [0.001, 0.002],
                 lambda v, seed, name: 0.5 + 0.001 * seed, fixed={"learn.phases": [3]})
    # a second sweep of the noise (one more value, and noise 64 again: taken once) joins the first
    more = sweep(tmp_path / "more", "cell.sensor_noise", [64, 256], lambda v, seed, name: 0.1)
    main = runpy.run_path(str(ROOT / "bench" / "star_vs_etar_sweep.py"))["main"]
    out = tmp_path / "out"
    assert main([str(noise), str(grid), str(more), "--baseline", "state_resolution=0", "--out", str(out)]) == 0
    table = (out / "star_vs_etar.md").read_text().splitlines()
    assert [line for line in table if line.startswith("## ")] == [
        f"## cell.sensor_noise ({noise}, {more})", f"## state_resolution ({grid})"]
    accuracy = [line for line in table if "filter accuracy" in line]
    assert accuracy.pop(2).startswith("| 256 |"), accuracy
    assert accuracy[0].startswith("| 1 |") and accuracy[0].endswith("| 3 / 0 / 0 | ETAR |"), accuracy
    assert accuracy[1].startswith("| 64 |") and accuracy[1].endswith("| 2 / 1 / 0 | no |"), accuracy
    # the grid sweep's 0 is the noise sweep's first value (noise 1): ETAR ahead there too
    assert accuracy[2].startswith("| 0 |") and accuracy[2].endswith("| 3 / 0 / 0 | ETAR |"), accuracy
    assert accuracy[3].startswith("| 0.001 |") and accuracy[3].endswith("| 0 / 0 / 3 | no |"), accuracy
    assert accuracy[4].startswith("| 0.002 |") and len(accuracy) == 5, accuracy
    assert "with learn.phases=3" in table  # given one value: said, not swept
    assert (out / "star_vs_etar.png").stat().st_size > 10_000

    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit) as exit_:
        main([str(tmp_path / "empty"), "--out", str(out)])
    assert exit_.value.code == 2
