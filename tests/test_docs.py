"""The references generated from the code are current: docs/messages.md from the messages,
docs/cli.md from the argparse parsers, docs/scenarios.md from the scenario's definition
and files.  A failure says the command that writes the file again."""

from pathlib import Path

import pytest

from services.cli.reference import reference as cli_reference
from services.runtime.messages import documentation as messages_reference
from services.scenario.reference import reference as scenario_reference

ROOT = Path(__file__).resolve().parents[1]

GENERATED = {
    "docs/messages.md": (messages_reference, "python -m services.runtime.messages > docs/messages.md"),
    "docs/cli.md": (cli_reference, "python -m services.cli.reference > docs/cli.md"),
    "docs/scenarios.md": (lambda: scenario_reference(ROOT / "scenarios"),
                          "python -m services.scenario.reference scenarios > docs/scenarios.md"),
}


@pytest.mark.parametrize("path", GENERATED)
def test_a_generated_reference_is_what_the_code_says(path):
    make, command = GENERATED[path]
    expected = make()
    actual = (ROOT / path).read_text()
    assert actual.rstrip("\n") == expected.rstrip("\n"), f"{path} is stale: run `{command}`"


def test_the_cli_reference_names_every_subcommand_and_every_flag():
    """The generator reads the parsers, not a list of its own: a subcommand or flag added
    to a parser appears in the reference."""
    from services.cli import bench

    text = cli_reference()
    parser = bench.build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, p in sub.choices.items():
        assert f"### `etar-bench {name}`" in text, name
        for action in p._actions:
            for flag in action.option_strings:
                if flag.startswith("--") and flag != "--help":
                    assert f"`{flag}" in text, (name, flag)


def test_the_scenario_reference_documents_every_key():
    from services.scenario.stages import STAGE_TYPES, CellSpec

    text = scenario_reference()
    for key in CellSpec.keys():
        assert f"| `{key}` |" in text, key
    for kind, cls in STAGE_TYPES.items():
        for name in cls.__dataclass_fields__:
            assert f"| `{name}` |" in text, (kind, name)


def test_the_lockstep_bench_guard_holds_to_the_ratio_the_benchmarks_page_states():
    import sys

    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import lockstep_rtf
    finally:
        sys.path.remove(str(ROOT / "bench"))
    stated = lockstep_rtf.stated_ratio()
    assert 1.0 < stated < 100.0, stated
    assert lockstep_rtf.guard_failure(stated, stated) is None
    assert lockstep_rtf.guard_failure(1.5 * stated, stated) is None
    failure = lockstep_rtf.guard_failure(1.51 * stated, stated)
    assert failure.startswith("GUARD FAILED") and "docs/benchmarks.md" in failure
