import dataclasses
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

from services.scenario import DEFAULT_STARTS, DemonstrateStage, LearnStage, ReproduceStage, Scenario
from services.scenario.checks import MAX_START_DRAWS, ScenarioError
from services.scenario.starts import demonstration_starts, reproduction_starts
from services.scenario.loading import load_scenario

SCENARIOS = Path(__file__).resolve().parents[3] / "scenarios"
SCENARIO_FILES = sorted(SCENARIOS.glob("*.yaml"))

MINIMAL = """\
name: t
world: valley
stages:
  - demonstrate:
      count: 2
  - learn:
  - reproduce:
      count: 3
"""


def write(tmp_path, text, name="x.yaml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def minimal(**overrides):
    data = {"name": "t", "world": "valley",
            "stages": [{"demonstrate": {"count": 2}}, {"learn": {}}, {"reproduce": {"count": 3}}]}
    data.update(overrides)
    return data


# --- the shipped scenarios -----------------------------------------------------------------

def test_there_are_scenario_files():
    assert {p.name for p in SCENARIO_FILES} >= {"valley.yaml", "valley_two_sides.yaml",
                                                 "hose_coupler.yaml", "smoke.yaml"}


@pytest.mark.parametrize("path", SCENARIO_FILES, ids=lambda p: p.name)
def test_every_scenario_file_loads_and_round_trips(path):
    scenario = load_scenario(path)
    assert scenario.name == path.stem
    assert scenario.source == str(path)
    assert path.read_text().startswith("#"), "each file opens with a comment saying what it is"
    assert Scenario.from_dict(scenario.to_dict(), source=scenario.source) == scenario


@pytest.mark.parametrize("path", SCENARIO_FILES, ids=lambda p: p.name)
def test_every_scenario_file_has_starts_that_can_be_drawn(path):
    scenario = load_scenario(path)
    demos = [s for stage in scenario.demonstrate_stages
             for s in demonstration_starts(stage, scenario.world, stage.seed)]
    for stage in scenario.reproduce_stages:
        assert len(reproduction_starts(stage, scenario.world, stage.seed, demos)) == stage.count


def test_valley_file_matches_thesis_6_1():
    s = load_scenario(SCENARIOS / "valley.yaml")
    demo, learn, repro = s.stages
    assert (s.world, s.clock, s.state, s.features) == ("valley", "lockstep", "position", "force")
    assert (demo.count, demo.sides, demo.start, demo.start_spread) == (6, ("left",), (0.68, -0.10, 0.40), 0.01)
    assert (learn.phases, learn.candidates, learn.criterion) == ("auto", (1, 2, 3, 4, 5, 6), "bic")
    assert (repro.count, repro.sides, repro.start_perturbation) == (20, ("left",), 0.03)


def test_valley_two_sides_file_demonstrates_three_from_each_side():
    s = load_scenario(SCENARIOS / "valley_two_sides.yaml")
    demo = s.demonstrate_stages[0]
    sides = [side for side, _ in demonstration_starts(demo, s.world, demo.seed)]
    assert sides.count("left") == sides.count("right") == 3
    assert set(s.reproduce_stages[0].sides) == {"left", "right"} and s.reproduce_stages[0].count == 20


def test_hose_coupler_file_matches_thesis_6_4():
    s = load_scenario(SCENARIOS / "hose_coupler.yaml")
    demo, learn, repro = s.stages
    assert (s.world, s.state, s.features) == ("hose_coupler", "pose", "force_torque")
    assert demo.count == 6 and demo.goal_x is None
    assert (learn.criterion, learn.phase_counts) == ("bic", (1, 2, 3, 4))
    assert (repro.count, repro.start_perturbation) == (10, 0.02)


def test_smoke_file_is_short():
    s = load_scenario(SCENARIOS / "smoke.yaml")
    demo, learn, repro = s.stages
    assert (demo.count, demo.max_seconds) == (2, 15.0)
    assert (learn.phases, learn.phase_counts, learn.restarts, learn.max_iter) == (3, (3,), 2, 60)
    assert (repro.count, repro.max_seconds) == (1, 15.0)
    # short episodes: low over the plate, stopping early along the groove
    assert demo.start[2] <= 0.30 and demo.goal_x >= 0.55 and repro.goal_x == demo.goal_x


# --- defaults, round trip, copies ------------------------------------------------------------

def test_defaults_are_filled_in(tmp_path):
    s = load_scenario(write(tmp_path, MINIMAL))
    assert (s.description, s.clock, s.seed, s.state, s.features) == ("", "lockstep", 0, "position", "force")
    demo, learn, repro = s.stages
    assert [st.kind for st in s.stages] == ["demonstrate", "learn", "reproduce"]
    assert demo == DemonstrateStage(count=2, sides=("left",), start=(0.68, -0.10, 0.40), start_spread=0.01,
                                    goal_x=0.42, max_seconds=40.0, seed=1000)
    assert learn == LearnStage(phases="auto", candidates=(1, 2, 3, 4, 5, 6), criterion="bic",
                               transitions="effect", restarts=4, max_iter=200, seed=0)
    assert repro == ReproduceStage(count=3, sides=("left",), start=(0.68, -0.10, 0.40), start_perturbation=0.03,
                                   min_distance_from_demonstrations=0.005, goal_x=0.42, goal_tolerance=0.01,
                                   max_contact_force=60.0, max_seconds=40.0, seed=2000)


def test_stage_seeds_follow_the_scenario_seed_and_differ_between_stages_of_a_kind():
    s = Scenario.from_dict(minimal(seed=7, stages=[
        {"demonstrate": {"count": 1}}, {"demonstrate": {"count": 1}}, {"demonstrate": {"count": 1, "seed": 3}},
        {"learn": None}, {"reproduce": {"count": 1}}, {"reproduce": {"count": 1}}]))
    assert [st.seed for st in s.stages] == [1007, 1008, 3, 7, 2007, 2008]


def test_hose_coupler_defaults():
    s = Scenario.from_dict(minimal(world="hose_coupler"))
    demo, _, repro = s.stages
    assert demo.start == repro.start == DEFAULT_STARTS["hose_coupler"] == (0.62, -0.08, 0.36)
    assert demo.goal_x is None and repro.goal_x is None
    assert "goal_x" not in s.to_dict()["stages"][0]["demonstrate"]


def test_values_are_normalised_to_immutable_plain_types():
    s = Scenario.from_dict(minimal(stages=[
        {"demonstrate": {"count": 1, "start": [1, -0.1, 0.4], "max_seconds": 5}},
        {"learn": {"candidates": [2, 3]}}]))
    demo, learn = s.stages
    assert demo.start == (1.0, -0.1, 0.4) and all(type(v) is float for v in demo.start)
    assert type(demo.max_seconds) is float and learn.candidates == (2, 3)
    assert isinstance(s.stages, tuple)
    with pytest.raises(dataclasses.FrozenInstanceError):
        demo.count = 3


def test_to_dict_round_trips_through_from_dict():
    s = Scenario.from_dict(minimal(description="d", clock="realtime", seed=5, state="pose", features="force_torque"))
    data = s.to_dict()
    assert "source" not in data
    assert Scenario.from_dict(data) == s
    assert Scenario.from_dict(data).to_dict() == data


def test_replace_returns_a_changed_copy_validated_and_keeps_defaults_defaults():
    s = Scenario.from_dict(minimal())
    r = s.replace("clock", "realtime")
    assert (s.clock, r.clock) == ("lockstep", "realtime")
    assert r.stages == s.stages and r.name == s.name
    with pytest.raises(ScenarioError, match=r"clock: expected one of 'lockstep', 'realtime', got 'wall'"):
        s.replace("clock", "wall")
    # a new seed reaches every stage that inherits it, not one that sets its own
    seeded = Scenario.from_dict(minimal(stages=[{"demonstrate": {"count": 1}},
                                                {"demonstrate": {"count": 1, "seed": 7}}]))
    assert [st.seed for st in seeded.replace("seed", 3).stages] == [1003, 7]
    # every stage of a kind, or the i-th
    assert [st.count for st in seeded.replace("demonstrate.count", 2).stages] == [2, 2]
    assert [st.count for st in seeded.replace("demonstrate[1].count", 4).stages] == [1, 4]
    assert seeded.replace("cell.sensor_noise", 2.0).cell.sensor_noise == 2.0
    for path, says in (("demonstrate[2].count", "the scenario has 2 demonstrate stage"),
                       ("learn.phases", "the scenario has no learn stage"),
                       ("teach.count", "STAGE one of demonstrate, learn, reproduce"),
                       ("cell.fri_packet_los", "did you mean 'fri_packet_loss'")):
        with pytest.raises(ScenarioError, match=says):
            seeded.replace(path, 1)


def test_constructors_validate_on_their_own():
    with pytest.raises(ScenarioError, match=r"^count: expected an integer >= 1 and <= 10000, got 0$"):
        DemonstrateStage(count=0)
    with pytest.raises(ScenarioError, match=r"^criterion: expected one of 'bic', 'aic', got 'mdl'$"):
        LearnStage(criterion="mdl")
    with pytest.raises(ScenarioError, match=r"^selection: expected one of 'per_demonstration', 'pooled', got 'mean'$"):
        LearnStage(selection="mean")
    assert LearnStage().selection == "per_demonstration" and LearnStage(selection="pooled").selection == "pooled"
    with pytest.raises(ScenarioError, match=r"<dict>: stages\[0\]: a learn stage needs a demonstrate stage"):
        Scenario(name="t", world="valley", stages=(LearnStage(),))


def test_phase_counts():
    assert LearnStage().phase_counts == (1, 2, 3, 4, 5, 6)
    assert LearnStage(phases=2, candidates=(1, 5)).phase_counts == (2,)


def test_exponent_floats_without_a_dot_are_numbers(tmp_path):
    s = load_scenario(write(tmp_path, MINIMAL.replace("count: 3", "count: 3\n      goal_tolerance: 5e-3")))
    assert s.reproduce_stages[0].goal_tolerance == 0.005


# --- errors: file, field path and value ------------------------------------------------------

ERROR_CASES = {
    "unknown top-level key": (
        MINIMAL.replace("name: t", "name: t\nnmae: u"), "nmae", "unknown key (did you mean 'name'?", "'nmae'"),
    "unknown stage key": (
        MINIMAL.replace("count: 2", "cuont: 2"), "stages[0].demonstrate.cuont", "did you mean 'count'?", "'cuont'"),
    "wrong type": (
        MINIMAL.replace("count: 2", "count: six"), "stages[0].demonstrate.count", "expected an integer >= 1",
        "'six'"),
    "float for an integer": (
        MINIMAL.replace("count: 3", "count: 3.0"), "stages[2].reproduce.count", "expected an integer >= 1", "3.0"),
    "bool for an integer": (
        MINIMAL.replace("count: 2", "count: yes"), "stages[0].demonstrate.count", "expected an integer", "True"),
    "bad enum": (
        MINIMAL.replace("world: valley", "world: moon"), "world", "expected one of 'valley', 'hose_coupler'",
        "'moon'"),
    "bad stage enum": (
        MINIMAL.replace("  - learn:", "  - learn:\n      transitions: star"), "stages[1].learn.transitions",
        "expected one of 'effect', 'state'", "'star'"),
    "negative count": (
        MINIMAL.replace("count: 3", "count: -1"), "stages[2].reproduce.count", "expected an integer >= 1", "-1"),
    "negative seed": (
        MINIMAL.replace("name: t", "name: t\nseed: -4"), "seed", "expected an integer >= 0", "-4"),
    "NaN": (
        MINIMAL.replace("count: 2", "count: 2\n      start_spread: .nan"), "stages[0].demonstrate.start_spread",
        "expected a finite number >= 0", "nan"),
    "an integer past float64's range": (
        MINIMAL.replace("count: 2", "count: 2\n      start: [1%s, 0.0, 0.4]" % ("0" * 400)),
        "stages[0].demonstrate.start[0]", "expected a finite number; this integer has 401 digits",
        "'an integer too large for a float'"),
    "restarts past the bound": (
        MINIMAL.replace("  - learn:", "  - learn:\n      restarts: 1%s" % ("0" * 400)), "stages[1].learn.restarts",
        "expected an integer >= 1 and <= 1000", "1" + "0" * 79 + "... (401 digits)"),
    "infinity in start": (
        MINIMAL.replace("count: 2", "count: 2\n      start: [0.7, .inf, 0.4]"), "stages[0].demonstrate.start[1]",
        "expected a finite number", "inf"),
    "zero tolerance": (
        MINIMAL.replace("count: 3", "count: 3\n      goal_tolerance: 0"), "stages[2].reproduce.goal_tolerance",
        "expected a finite number > 0", "0"),
    "start with 2 numbers": (
        MINIMAL.replace("count: 2", "count: 2\n      start: [0.68, -0.10]"), "stages[0].demonstrate.start",
        "expected exactly 3 numbers", "[0.68, -0.1]"),
    "phases spelt out": (
        MINIMAL.replace("  - learn:", "  - learn:\n      phases: three"), "stages[1].learn.phases",
        "expected 'auto' or an integer >= 1", "'three'"),
    "duplicate candidates": (
        MINIMAL.replace("  - learn:", "  - learn:\n      candidates: [1, 2, 2]"), "stages[1].learn.candidates",
        "expected distinct phase counts", "[1, 2, 2]"),
    "a side that is a string": (
        MINIMAL.replace("count: 2", "count: 2\n      sides: left"), "stages[0].demonstrate.sides",
        "expected a list of sides", "'left'"),
    "bad side": (
        MINIMAL.replace("count: 2", "count: 2\n      sides: [left, up]"), "stages[0].demonstrate.sides[1]",
        "expected one of 'left', 'right'", "'up'"),
    "wrong stage order": (
        MINIMAL.replace("  - learn:\n", "").replace("  - demonstrate:", "  - learn:\n  - demonstrate:"),
        "stages[0]", "a learn stage needs a demonstrate stage before it", "['learn', 'demonstrate', 'reproduce']"),
    "demonstrate after learn": (
        MINIMAL + "  - demonstrate:\n      count: 1\n", "stages[3]",
        "a demonstrate stage must come before the learn and reproduce stages",
        "['demonstrate', 'learn', 'reproduce', 'demonstrate']"),
    "missing learn before reproduce": (
        MINIMAL.replace("  - learn:\n", ""), "stages[1]", "a reproduce stage needs a learn stage before it",
        "['demonstrate', 'reproduce']"),
    "two learn stages": (
        MINIMAL.replace("  - learn:\n", "  - learn:\n  - learn:\n"), "stages[2]", "only one learn stage",
        "['demonstrate', 'learn', 'learn', 'reproduce']"),
    "unknown stage kind": (
        MINIMAL.replace("  - learn:", "  - lern:"), "stages[1]", "unknown stage kind", "'lern'"),
    "stage with two kinds": (
        MINIMAL.replace("  - learn:", "  - learn:\n    reproduce:"), "stages[1]",
        "expected a mapping with exactly one key", "{'learn': None, 'reproduce': None}"),
    "empty stages": (
        "name: t\nworld: valley\nstages: []\n", "stages", "expected a non-empty list of stages", "[]"),
    "right side in the hose coupler": (
        MINIMAL.replace("world: valley", "world: hose_coupler").replace("count: 2", "count: 2\n      sides: [right]"),
        "stages[0].demonstrate.sides", "the hose_coupler world has one side", "['right']"),
    "goal_x in the hose coupler": (
        MINIMAL.replace("world: valley", "world: hose_coupler").replace("count: 3", "count: 3\n      goal_x: 0.4"),
        "stages[2].reproduce.goal_x", "applies to the valley world only", "0.4"),
    "left start on the right side": (
        MINIMAL.replace("count: 2", "count: 2\n      start: [0.68, 0.10, 0.40]"), "stages[0].demonstrate.start",
        "the valley's left side is y < 0", "[0.68, 0.1, 0.4]"),
    "goal beyond the start": (
        MINIMAL.replace("count: 3", "count: 3\n      goal_x: 0.7"), "stages[2].reproduce.goal_x",
        "goal_x must lie below every start's x", "0.7"),
}


@pytest.mark.parametrize("case", ERROR_CASES, ids=str)
def test_errors_name_file_field_path_and_value(tmp_path, case):
    text, field_path, problem, value = ERROR_CASES[case]
    path = write(tmp_path, text)
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    err = caught.value
    message = str(err)
    assert message.startswith(f"{path}: {field_path}: "), message
    assert problem in message, message
    assert message.endswith(f", got {value}"), message
    assert (err.source, err.path) == (str(path), field_path)


def test_error_message_has_the_documented_form(tmp_path):
    path = write(tmp_path, MINIMAL.replace("  - learn:", "  - learn:\n      phases: three"))
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    assert str(caught.value) == (f"{path}: stages[1].learn.phases: expected 'auto' or an integer >= 1 "
                                 f"and <= 20, got 'three'")
    assert isinstance(caught.value, ValueError)


@pytest.mark.parametrize("field", ["name", "world", "stages"])
def test_missing_required_field(tmp_path, field):
    lines = [line for line in MINIMAL.splitlines(keepends=True) if not line.startswith(f"{field}:")]
    if field == "stages":
        lines = ["name: t\n", "world: valley\n"]
    path = write(tmp_path, "".join(lines))
    with pytest.raises(ScenarioError, match=rf"^{path}: {field}: required field is missing$"):
        load_scenario(path)


def test_missing_stage_count(tmp_path):
    path = write(tmp_path, MINIMAL.replace("      count: 3\n", ""))
    with pytest.raises(ScenarioError, match=rf"^{path}: stages\[2\]\.reproduce\.count: required field is missing$"):
        load_scenario(path)


def test_a_count_or_a_time_limit_beyond_reason_is_refused_before_anything_starts(tmp_path):
    path = write(tmp_path, MINIMAL.replace("      count: 3\n", "      count: 1000000000000\n"))
    with pytest.raises(ScenarioError, match=rf"^{path}: stages\[2\]\.reproduce\.count: expected an integer >= 1 "
                                            rf"and <= 10000, got 1000000000000$"):
        load_scenario(path)
    path = write(tmp_path, MINIMAL.replace("      count: 3\n", "      count: 3\n      max_seconds: 1e9\n"))
    with pytest.raises(ScenarioError, match=rf"^{path}: stages\[2\]\.reproduce\.max_seconds: expected at most "
                                            rf"3600 s of simulated time per episode"):
        load_scenario(path)


def test_yaml_syntax_error_names_the_file_and_line(tmp_path):
    path = write(tmp_path, "name: t\nworld: valley\nstages:\n  - demonstrate: {count: 2\n  - learn:\n")
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    # The parser notices the unclosed brace on line 5; the message also says where it opened.
    assert str(caught.value).startswith(f"{path}:5: invalid YAML: ")
    assert str(caught.value).endswith("while parsing a flow mapping on line 4")
    assert caught.value.line == 5


def test_yaml_bad_indentation_names_the_line(tmp_path):
    path = write(tmp_path, "name: t\nworld: valley\n  clock: lockstep\n")
    with pytest.raises(ScenarioError, match=rf"^{path}:3: invalid YAML: mapping values are not allowed here"):
        load_scenario(path)


def test_duplicate_key_names_both_lines(tmp_path):
    path = write(tmp_path, MINIMAL.replace("count: 2", "count: 2\n      count: 4"))
    with pytest.raises(ScenarioError, match=rf"^{path}:6: invalid YAML: duplicate key 'count' \(first on line 5\)"):
        load_scenario(path)


@pytest.mark.parametrize("text", ["", "# only a comment\n", "\n\n"])
def test_empty_file(tmp_path, text):
    path = write(tmp_path, text)
    with pytest.raises(ScenarioError, match=rf"^{path}: the file is empty"):
        load_scenario(path)


@pytest.mark.parametrize("text, value", [("- a\n- b\n", "['a', 'b']"), ("just words\n", "'just words'")])
def test_top_level_must_be_a_mapping(tmp_path, text, value):
    path = write(tmp_path, text)
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    assert str(caught.value) == f"{path}: expected a mapping of scenario fields at the top level, got {value}"


def test_missing_file(tmp_path):
    path = tmp_path / "absent.yaml"
    with pytest.raises(ScenarioError, match=rf"^{path}: cannot read the file"):
        load_scenario(path)


def test_from_dict_names_its_source():
    with pytest.raises(ScenarioError, match=r"^cfg: clock: expected one of 'lockstep', 'realtime', got 'fast'$"):
        Scenario.from_dict(minimal(clock="fast"), source="cfg")


# --- start positions ---------------------------------------------------------------------------

def test_demonstration_starts_are_deterministic_for_a_seed():
    stage = DemonstrateStage(count=5, sides=("left", "right"))
    a = demonstration_starts(stage, "valley", 3)
    assert a == demonstration_starts(stage, "valley", 3)
    assert a != demonstration_starts(stage, "valley", 4)


def test_demonstration_starts_cycle_sides_mirror_y_and_stay_within_the_spread():
    stage = DemonstrateStage(count=40, sides=("left", "right"), start=(0.68, -0.10, 0.40), start_spread=0.01)
    starts = demonstration_starts(stage, "valley", 0)
    assert [side for side, _ in starts] == ["left", "right"] * 20
    for side, xyz in starts:
        nominal = np.array([0.68, -0.10 if side == "left" else 0.10, 0.40])
        assert np.all(np.abs(np.array(xyz) - nominal) <= 0.01)
    assert all(xyz[1] < 0 for side, xyz in starts if side == "left")
    assert all(xyz[1] > 0 for side, xyz in starts if side == "right")


def test_right_side_is_the_mirror_image_without_spread():
    stage = DemonstrateStage(count=2, sides=("left", "right"), start=(0.7, -0.12, 0.41), start_spread=0.0)
    assert demonstration_starts(stage, "valley", 0) == [("left", (0.7, -0.12, 0.41)), ("right", (0.7, 0.12, 0.41))]


def test_demonstration_starts_use_the_world_default_start():
    stage = DemonstrateStage(count=3, start_spread=0.0)
    assert [xyz for _, xyz in demonstration_starts(stage, "hose_coupler", 0)] == [(0.62, -0.08, 0.36)] * 3


def test_reproduction_starts_are_deterministic_and_depend_on_the_seed():
    demos = demonstration_starts(DemonstrateStage(count=6, sides=("left", "right")), "valley", 1)
    stage = ReproduceStage(count=10, sides=("left", "right"))
    a = reproduction_starts(stage, "valley", 9, demos)
    assert a == reproduction_starts(stage, "valley", 9, demos)
    assert a != reproduction_starts(stage, "valley", 10, demos)


def test_reproduction_starts_stay_in_the_box_and_away_from_demonstrations():
    # A wide exclusion against a dense set of demonstrations forces many redraws.
    demo = DemonstrateStage(count=60, sides=("left", "right"), start_spread=0.02)
    demos = demonstration_starts(demo, "valley", 2)
    stage = ReproduceStage(count=100, sides=("left", "right"), start_perturbation=0.03,
                           min_distance_from_demonstrations=0.01)
    starts = reproduction_starts(stage, "valley", 5, demos)
    assert [side for side, _ in starts] == ["left", "right"] * 50
    for side, xyz in starts:
        nominal = np.array([0.68, -0.10 if side == "left" else 0.10, 0.40])
        assert np.all(np.abs(np.array(xyz) - nominal) <= 0.03)
        same_side = np.array([d for s, d in demos if s == side])
        assert np.linalg.norm(same_side - np.array(xyz), axis=1).min() >= 0.01


def test_reproduction_starts_ignore_demonstrations_of_the_other_side():
    # A right-side demonstration exactly at the mirrored nominal start does not push a
    # left reproduction away (and a zero perturbation draws the nominal start itself).
    demos = [("right", (0.68, -0.10, 0.40))]
    stage = ReproduceStage(count=1, start_perturbation=0.0)
    assert reproduction_starts(stage, "valley", 0, demos) == [("left", (0.68, -0.10, 0.40))]


def test_reproduction_starts_refuse_a_perturbation_too_small_for_the_distance():
    demos = [("left", (0.68, -0.10, 0.40))]
    stage = ReproduceStage(count=1, start_perturbation=0.001, min_distance_from_demonstrations=0.005)
    with pytest.raises(ScenarioError) as caught:
        reproduction_starts(stage, "valley", 0, demos)
    message = str(caught.value)
    assert message.startswith("start_perturbation: reproduction 0 (left side)")
    assert f"{MAX_START_DRAWS} draws" in message and "the perturbation is too small" in message
    assert message.endswith("got 0.001")


def test_start_functions_check_the_world():
    with pytest.raises(ScenarioError, match=r"^world: expected one of 'valley', 'hose_coupler', got 'moon'$"):
        demonstration_starts(DemonstrateStage(count=1), "moon", 0)
    with pytest.raises(ScenarioError, match=r"^sides: the hose_coupler world has one side"):
        demonstration_starts(DemonstrateStage(count=1, sides=("right",)), "hose_coupler", 0)


def test_starts_are_finite_floats():
    for side, xyz in demonstration_starts(DemonstrateStage(count=3), "valley", 0):
        assert len(xyz) == 3 and all(type(v) is float and math.isfinite(v) for v in xyz)


# --- a stored model instead of a learn stage; holding the goal -------------------------------

MODEL_ONLY = """\
name: t
world: valley
model: models/m.json
stages:
  - reproduce:
      count: 1
      stop_at_goal: false
"""


def test_a_model_file_replaces_the_learn_stage_and_resolves_beside_the_scenario(tmp_path):
    s = load_scenario(write(tmp_path, MODEL_ONLY))
    assert s.model == "models/m.json" and s.learn_stage is None
    assert s.model_path() == tmp_path / "models" / "m.json"
    assert s.reproduce_stages[0].stop_at_goal is False
    assert Scenario.from_dict(s.to_dict(), source=s.source) == s
    assert "model" not in load_scenario(write(tmp_path, MINIMAL, "y.yaml")).to_dict()
    assert load_scenario(write(tmp_path, MINIMAL, "z.yaml")).reproduce_stages[0].stop_at_goal is True


def test_a_model_and_a_learn_stage_conflict(tmp_path):
    path = write(tmp_path, MINIMAL.replace("name: t", "name: t\nmodel: m.json"))
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    assert caught.value.path == "stages[1]" and "does not learn" in str(caught.value)


@pytest.mark.parametrize("text, field_path, problem", [
    (MODEL_ONLY.replace("stop_at_goal: false", "stop_at_goal: 0"), "stages[0].reproduce.stop_at_goal",
     "expected true or false"),
    (MODEL_ONLY.replace("model: models/m.json", "model: ''"), "model", "expected a non-empty string"),
    (MODEL_ONLY.replace("name: t", "name: my smoke"), "name", "use 1-55 letters, digits, '-' or '_'"),
    (MODEL_ONLY.replace("name: t", "name: " + "x" * 56), "name", "use 1-55 letters, digits, '-' or '_'"),
])
def test_model_and_stop_at_goal_are_checked(tmp_path, text, field_path, problem):
    with pytest.raises(ScenarioError) as caught:
        load_scenario(write(tmp_path, text))
    assert caught.value.path == field_path and problem in str(caught.value)


def test_hold_file_reproduces_with_the_stored_smoke_model_for_a_minute():
    s = load_scenario(SCENARIOS / "hold.yaml")
    (repro,) = s.stages
    assert (s.clock, repro.max_seconds, repro.stop_at_goal) == ("realtime", 60.0, False)
    assert s.model_path().is_file()
    from etar import ETAR

    meta = ETAR.load(s.model_path()).metadata
    assert len(meta["goal"]) == 3 and meta["impedance"] and meta["phase_to_truth"]


def test_restart_policies_are_parsed_and_limited_to_where_a_restart_is_meaningful():
    s = Scenario.from_dict(minimal(restart={"recorder": "on_failure", "phase_estimator": "never"}))
    assert s.restart == (("phase_estimator", "never"), ("recorder", "on_failure"))
    assert Scenario.from_dict(s.to_dict()) == s
    assert Scenario.from_dict(minimal()).restart == () and "restart" not in Scenario.from_dict(minimal()).to_dict()
    for bad, says in (({"robot": "on_failure"}, "restart.robot: a restart is meaningful for phase_estimator and "
                                                "recorder only"),
                      ({"recorder": "always"}, "restart.recorder: expected one of 'never', 'on_failure'"),
                      (["recorder"], "restart: expected a mapping of role: policy")):
        with pytest.raises(ScenarioError, match=says):
            Scenario.from_dict(minimal(restart=bad), "x.yaml")


def test_the_roles_a_scenario_needs_come_from_the_roles_table():
    """services.runtime.roles is the one list of which roles the cell and each kind of stage
    need; every stage kind has its entry there, and every role it names exists."""
    from services.runtime.roles import CELL_ROLES, ROLES, STAGE_ROLES
    from services.scenario.stages import STAGE_TYPES

    assert set(STAGE_ROLES) == set(STAGE_TYPES)
    assert set(CELL_ROLES).union(*STAGE_ROLES.values()) <= set(ROLES)
    assert load_scenario(SCENARIOS / "hold.yaml").roles == CELL_ROLES + STAGE_ROLES["reproduce"]
    assert load_scenario(SCENARIOS / "smoke.yaml").roles == (CELL_ROLES + STAGE_ROLES["demonstrate"]
                                                         + STAGE_ROLES["reproduce"])
