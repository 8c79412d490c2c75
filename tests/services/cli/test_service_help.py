"""What a person reads from a service program: its --help (the node's documentation without
reST markup or the code's constant names, every flag explained with its default) and its
--version (one line: the program and the package's version)."""

import argparse
import re
import subprocess
import sys
from importlib import metadata

import pytest

from services.cli import roles
from services.cli.version import add_version_argument
from services.runtime.messages import HOLD_WATCH_S
from services.runtime.provenance import _code, code, code_text
from services.runtime.roles import ROLES

# a constant's name as the code spells it (LOCKSTEP_LATENCY_NS); an environment variable
# ($ETAR_ZENOH_CONNECT) and the scheduling policy's own name are what a user types
CONSTANT = re.compile(r"(?<!\$)\b[A-Z][A-Z0-9]+_[A-Z0-9_]+\b")
USER_WORDS = {"SCHED_FIFO"}


def help_of(role: str) -> str:
    return roles.build_parser(role).format_help()


@pytest.mark.parametrize("role", ROLES)
def test_the_help_has_no_markup_and_no_constant_names(role):
    text = help_of(role)
    assert "``" not in text
    assert set(CONSTANT.findall(text)) <= USER_WORDS, CONSTANT.findall(text)


@pytest.mark.parametrize("role", ROLES)
def test_every_flag_is_explained_with_its_default(role):
    parser = roles.build_parser(role)
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or action.option_strings == ["--version"]:
            continue
        flag = action.option_strings[-1]
        assert action.help and len(action.help) > 10, flag
        if not action.required and action.nargs != 0:
            assert "default" in action.help, (flag, action.help)
    # a value's name says what it is, not the field it fills
    usage = parser.format_usage()
    assert not re.search(r"[A-Z]+_[A-Z]+", usage), usage


def test_the_help_renders_the_docstring_without_markup():
    assert roles.help_text("reads ``robot/state`` and ``ft/wrench``") == "reads robot/state and ft/wrench"
    assert roles.help_text(None) == ""


def test_the_numbers_the_help_states_are_the_code_s():
    """The help says numbers where the docstrings once named constants: they must stay true."""
    from etar.policy import HOLD_STIFFNESS
    from services.nodes import impedance_commander, recorder, robot
    from services.runtime.messages import MAX_PAYLOAD_BYTES
    from services.runtime.visual_topics import MAX_VISUAL_RATE_HZ

    assert robot.LOCKSTEP_LATENCY_NS == 100_000 and "0.1 ms" in robot.__doc__
    assert impedance_commander.ESTIMATE_WAIT_S == 2.0 and "after 2 s" in impedance_commander.__doc__
    assert impedance_commander.STALE_ESTIMATE_CYCLES == 50 and "50 cycles" in impedance_commander.__doc__
    assert HOLD_STIFFNESS == 2000.0 and "2000 N/m" in impedance_commander.__doc__
    assert HOLD_WATCH_S == 1.0 and "lasted 1 s" in impedance_commander.__doc__
    assert MAX_PAYLOAD_BYTES == 64 * 1024 and "64 KiB" in recorder.__doc__
    assert MAX_VISUAL_RATE_HZ == 1000 and "(1000)" in help_of("recorder") and "(1000)" in help_of("foxglove_bridge")


def installed_version() -> str:
    try:
        return metadata.version("etar-testbench")
    except metadata.PackageNotFoundError:
        return "unknown"


VERSION_LINE = r"(?P<program>\S+) (?P<version>\S+)( \(git [0-9a-f]{7}(, uncommitted changes)?\))?"


@pytest.mark.parametrize("role", ROLES)
def test_version_is_one_line_with_the_program_and_the_version(capsys, role):
    program = ROLES[role].program
    with pytest.raises(SystemExit) as done:
        roles.main(role, ["--version"])
    assert done.value.code == 0
    out, err = capsys.readouterr()
    assert err == "" and out.endswith("\n") and out.count("\n") == 1, out
    m = re.fullmatch(VERSION_LINE, out.strip())
    assert m and m["program"] == program and m["version"] == installed_version(), out


def test_version_from_the_console_script():
    done = subprocess.run([sys.executable, "-m", "services.cli.roles", "robot", "--version"], capture_output=True,
                          text=True, timeout=120, check=False)
    assert done.returncode == 0 and done.stderr == "", done
    assert re.fullmatch(VERSION_LINE, done.stdout.strip()) and done.stdout.startswith("etar-robot ")


def test_version_outside_a_checkout_has_no_commit(tmp_path):
    assert code(tmp_path) == {"version": installed_version(), "commit": None, "dirty": None}
    assert code_text(tmp_path) == installed_version()


def test_version_names_the_commit_and_a_changed_tree(tmp_path):
    git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]
    try:
        subprocess.run([*git, "init", "-q"], check=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        pytest.skip("no git here")
    (tmp_path / "a.txt").write_text("1\n")
    subprocess.run([*git, "add", "a.txt"], check=True, timeout=30)
    subprocess.run([*git, "commit", "-q", "-m", "one"], check=True, timeout=30)
    clean = code(tmp_path)
    assert re.fullmatch(r"[0-9a-f]{40}", clean["commit"]) and clean["dirty"] is False
    (tmp_path / "untracked.txt").write_text("new\n")
    _code.cache_clear()
    assert code(tmp_path) == clean  # an untracked file changes nothing the program runs
    (tmp_path / "a.txt").write_text("2\n")
    _code.cache_clear()
    assert code(tmp_path) == dict(clean, dirty=True)
    assert code_text(tmp_path) == f"{installed_version()} (git {clean['commit'][:7]}, uncommitted changes)"


def test_add_version_argument_works_on_any_parser(capsys):
    parser = argparse.ArgumentParser(prog="etar-bench")
    add_version_argument(parser, "etar-bench")
    with pytest.raises(SystemExit) as done:
        parser.parse_args(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith(f"etar-bench {installed_version()}")
