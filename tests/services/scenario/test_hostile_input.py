"""Hostile scenario files: each is one ScenarioError line naming the file (exit 2 from
`etar-bench check`), never a traceback, a megabyte of message or a hang."""

import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from services.scenario import Scenario
from services.scenario.checks import MAX_QUOTED, ScenarioError, quoted
from services.scenario.loading import MAX_FILE_BYTES, MAX_NESTING, MAX_VALUES, load_scenario

ROOT = Path(__file__).resolve().parents[3]
SMOKE = (ROOT / "scenarios" / "smoke.yaml").read_text()
DESCRIPTION = 'description: "Short valley run for tests: 2 demonstrations, 3 fixed phases, 1 reproduction"'


def write(tmp_path, text, name="x.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def refused(path) -> str:
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path)
    message = str(caught.value)
    assert "\n" not in message and message.startswith(f"{path}"), message
    return message


def bomb(levels: int, width: int = 9) -> str:
    """A billion laughs in flow style: each level a list of ``width`` aliases of the one below."""
    text = "&a0 [" + ", ".join(["lol"] * width) + "]"
    for i in range(1, levels + 1):
        text = f"&a{i} [" + ", ".join([text] + [f"*a{i - 1}"] * (width - 1)) + "]"
    return text[text.index(" ") + 1:]  # the outermost needs no anchor


def check(path, timeout: float = 60) -> subprocess.CompletedProcess:
    """`etar-bench check PATH` in a process that cannot take the machine with it (2 GB, a timeout)."""
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))

    return subprocess.run([sys.executable, "-c", "import sys; from services.cli.bench import main; "
                           "sys.exit(main(['check', sys.argv[1]]))", str(path)], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout, preexec_fn=limit)


# --- 1. nesting ------------------------------------------------------------------------------

@pytest.mark.parametrize("value", ["[" * 5000 + "]" * 5000, "{a: " * 3000 + "1" + "}" * 3000],
                         ids=["lists", "mappings"])
def test_deeply_nested_yaml_is_one_line_not_a_recursion_error(tmp_path, value):
    path = write(tmp_path, SMOKE + f"bogus: {value}\n")
    message = refused(path)
    assert f"nested too deeply: more than {MAX_NESTING} levels" in message
    assert message.startswith(f"{path}:27: invalid YAML: "), message


def test_nesting_and_values_up_to_the_bounds_are_yaml_the_scenario_then_judges(tmp_path):
    """At the bounds the YAML is read and the scenario's own checks speak (the unknown key),
    and anchors and aliases in a real scenario are fine."""
    deepest = MAX_NESTING - 1  # the top-level mapping is the first level
    message = refused(write(tmp_path, SMOKE + "bogus: " + "[" * (deepest - 1) + "1" + "]" * (deepest - 1) + "\n"))
    assert "bogus: unknown key" in message and "nested too deeply" not in message, message
    values = MAX_VALUES - SMOKE.count(":") * 2 - 50  # the smoke's own values, with room to spare
    message = refused(write(tmp_path, SMOKE + "bogus: [" + ", ".join(["1"] * values) + "]\n", "many.yaml"))
    assert "bogus: unknown key" in message and f"more than {MAX_VALUES}" not in message, message
    anchored = SMOKE.replace("start: [0.60, -0.04, 0.27]", "start: &s [0.60, -0.04, 0.27]", 1)
    anchored = anchored.replace("start: [0.60, -0.04, 0.27]", "start: *s", 1)
    assert anchored.count("*s") == 1
    assert load_scenario(write(tmp_path, anchored, "anchored.yaml")).stages == \
        load_scenario(ROOT / "scenarios" / "smoke.yaml").stages


def test_nesting_through_aliases_counts_the_levels_they_stand_for(tmp_path):
    # each anchor is 20 levels deep, within the bound; three of them in a row are 60
    levels = 20
    text = SMOKE + "".join(f"n{i}: &n{i} " + "[" * levels + (f"*n{i - 1}" if i else "1") + "]" * levels + "\n"
                           for i in range(3))
    assert "nested too deeply" in refused(write(tmp_path, text))


def test_a_recursive_alias_is_refused(tmp_path):
    message = refused(write(tmp_path, SMOKE.replace("name: smoke", "name: &r [*r]")))
    assert "the alias *r is inside its own anchor" in message


def test_cli_check_of_deep_nesting_exits_2_with_one_line(tmp_path):
    path = write(tmp_path, SMOKE + "bogus: " + "[" * 5000 + "]" * 5000 + "\n")
    done = check(path)
    assert done.returncode == 2, done.stderr[-500:]
    assert done.stderr.splitlines() == [f"etar-bench check: error: {path}:27: invalid YAML: nested too deeply: "
                                        f"more than {MAX_NESTING} levels (column 39)"]  # the 33rd level


# --- 2. long values and anchor bombs ------------------------------------------------------------

@pytest.mark.parametrize("field, replace", [
    ("description", DESCRIPTION), ("name", "name: smoke"),
    ("stages[0].demonstrate.start", "start: [0.60, -0.04, 0.27]"),
], ids=["description", "name", "start"])
def test_a_value_in_an_error_is_cut_to_a_line(tmp_path, field, replace):
    key = replace.split(":")[0]
    path = write(tmp_path, SMOKE.replace(replace, f"{key}: {bomb(3)}", 1))  # 9**4 values: within the bound
    message = refused(path)
    assert f": {field}: expected " in message
    assert message.endswith("... (a list of 9 items)"), message
    assert len(message) < len(str(path)) + len(field) + 200, message


def test_an_anchor_bomb_is_refused_before_it_is_expanded(tmp_path):
    # 9**10: 3.5 billion values, in a process of its own: expanded, it would fill the machine
    path = write(tmp_path, SMOKE.replace(DESCRIPTION, f"description: {bomb(9)}"))
    done = check(path, timeout=30)
    assert done.returncode == 2, done.stderr[-500:]
    (line,) = done.stderr.splitlines()
    assert line.startswith(f"etar-bench check: error: {path}:5: invalid YAML: more than {MAX_VALUES} values, "
                           "each alias counted as the values it stands for"), line


def test_a_long_string_is_quoted_by_its_start_and_length(tmp_path):
    message = refused(write(tmp_path, SMOKE.replace("name: smoke", "name: " + "n" * 100_000)))
    assert message.endswith(", got '" + "n" * (MAX_QUOTED - 1) + "... (100000 characters)"), message[-200:]


def test_an_integer_past_pythons_digits_is_one_line(tmp_path):
    message = refused(write(tmp_path, SMOKE.replace("count: 2", "count: 1" + "0" * 6000)))
    assert "an integer of 6001 digits" in message


def test_a_long_unknown_key_is_cut_in_the_path_too(tmp_path):
    message = refused(write(tmp_path, SMOKE + "? " + "k" * 5000 + "\n: 1\n"))
    assert ": unknown key (" in message and len(message) < len(str(tmp_path)) + 500, message


def test_a_control_character_is_one_line_with_its_place(tmp_path):
    path = write(tmp_path, SMOKE.replace("world: valley", "world: \x01"))
    assert refused(path) == (f"{path}:6: invalid YAML: unacceptable character #x0001: special characters are not "
                             "allowed (column 8)")


def test_quoted_walks_no_further_than_it_prints():
    deep: list = []
    for _ in range(100_000):  # deeper than repr() can go
        deep = [deep]
    loop: list = [1]
    loop.append(loop)
    shared = [["x"] * 10] * 10
    for _ in range(4):  # a million items if expanded, as YAML's aliases share them
        shared = [shared] * 10
    for value in (deep, loop, shared):
        text = quoted(value)
        assert len(text) < MAX_QUOTED + 40, text
    assert quoted([0.6, -0.04, 0.27]) == repr([0.6, -0.04, 0.27])
    assert quoted({"a": (1,), "b": None}) == repr({"a": (1,), "b": None})
    assert quoted("x" * MAX_QUOTED) == repr("x" * MAX_QUOTED)[:MAX_QUOTED] + f"... ({MAX_QUOTED} characters)"


def test_from_dict_and_replace_quote_a_deep_value_in_one_short_line():
    deep: list = []
    for _ in range(10_000):
        deep = [deep]
    base = {"name": "t", "world": "valley", "stages": [{"demonstrate": {"count": 2}}]}
    with pytest.raises(ScenarioError) as caught:
        Scenario.from_dict(dict(base, description=deep))
    assert len(str(caught.value)) < 200
    with pytest.raises(ScenarioError) as caught:
        Scenario.from_dict(base).replace("description", deep)
    assert len(str(caught.value)) < 300


# --- 3. what is not a regular file ---------------------------------------------------------------

@pytest.mark.parametrize("device", ["/dev/zero", "/dev/urandom"])
def test_a_device_is_refused_without_reading_it(device):
    if not os.path.exists(device):
        pytest.skip(f"no {device}")
    done = check(device, timeout=30)
    assert (done.returncode, done.stderr.splitlines()) == (
        2, [f"etar-bench check: error: {device}: not a regular file (a character device), expected a scenario file"])


def test_a_fifo_is_refused_without_waiting_for_a_writer(tmp_path):
    fifo = tmp_path / "x.yaml"
    os.mkfifo(fifo)
    done = check(fifo, timeout=30)
    assert (done.returncode, done.stderr.splitlines()) == (
        2, [f"etar-bench check: error: {fifo}: not a regular file (a FIFO), expected a scenario file"])


def test_a_directory_is_not_a_regular_file(tmp_path):
    assert refused(tmp_path) == f"{tmp_path}: not a regular file (a directory), expected a scenario file"


def test_a_file_past_the_cap_is_refused_by_its_size(tmp_path):
    path = write(tmp_path, SMOKE + "#" + "x" * MAX_FILE_BYTES + "\n")
    size = path.stat().st_size
    assert refused(path) == (f"{path}: the file is {size} bytes, more than the {MAX_FILE_BYTES} a scenario may be "
                             "(a scenario is a few kB)")


# --- 4. the number of phases ------------------------------------------------------------------------

@pytest.mark.parametrize("text, field, value", [
    ("phases: 100000", "stages[1].learn.phases", "100000"),
    ("phases: auto\n      candidates: [2, 100000]", "stages[1].learn.candidates[1]", "100000"),
])
def test_the_number_of_phases_has_an_upper_bound(tmp_path, text, field, value):
    path = write(tmp_path, SMOKE.replace("phases: 3", text))
    message = refused(path)
    assert message.startswith(f"{path}: {field}: expected ") and "<= 20" in message, message
    assert message.endswith(f", got {value}"), message


def test_twenty_phases_are_accepted(tmp_path):
    assert load_scenario(write(tmp_path, SMOKE.replace("phases: 3", "phases: 20"))).learn_stage.phases == 20


# --- 5. an empty path ---------------------------------------------------------------------------------

def test_an_empty_path_says_so():
    with pytest.raises(ScenarioError) as caught:
        load_scenario("")
    assert str(caught.value) == "'': an empty path, expected a scenario file"
