"""Every flag has one spelling: docs/flags.md's table matches the parsers, and a spelling that is
not a flag is refused."""

import argparse

import pytest

from fdnet.cli import build_parser, main


@pytest.mark.parametrize(
    "argv",
    [
        ["synth", "--out", "route", "--frames", "3"],
        ["demo", "--train-minutes", "1"],
        ["groundtruth", "--aligned", "--out", "gt.csv", "--tolerance-frames", "2"],
        ["database", "build", "--images", "map", "--db", "map.db", "--method", "sad", "--out", "other.db"],
        ["evaluate", "--methods", "sad"],
    ],
)
def test_a_spelling_that_is_not_a_flag_is_refused(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    assert f"unrecognized arguments: {' '.join(argv[-2:])}" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())  # refused before anything was written


def _leaf_parsers():
    """{"database build": parser, "synth": parser, ...} for every (sub-)command."""
    found = {}

    def walk(parser, name):
        nested = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        for action in nested:
            for sub_name, sub in action.choices.items():
                walk(sub, f"{name} {sub_name}".strip())
        if not nested:
            found[name] = parser

    walk(build_parser(), "")
    return found


def _table_rows():
    from pathlib import Path

    def flag_table(text: str) -> list[str]:
        lines = text.splitlines()
        start = lines.index("| flag | meaning | commands |")
        end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
        return [line for line in lines[start:end] if line.startswith("| `--")]

    root = Path(__file__).resolve().parents[2]
    tables = [flag_table((root / name).read_text()) for name in ("docs/flags.md", "docs/guide.md")]
    assert tables[0] == tables[1], "docs/guide.md's flag table differs from docs/flags.md's"
    rows = [line.removesuffix(" |").split(" | ") for line in tables[0]]
    assert len(rows) >= 20
    return rows


def test_the_flag_table_matches_the_parsers():
    import re

    parsers = _leaf_parsers()
    for flag_cell, _, commands in _table_rows():
        flags = re.findall(r"`(--[a-z0-9-]+)", flag_cell)
        if "every command" in commands:
            continue
        for command in re.split(r",\s*", commands.split(" (")[0]):
            if "/" in command:  # "database add/build/query"
                first, rest = command.split(" ", 1)
                names = [f"{first} {n}" for n in rest.split("/")]
            else:
                names = [command]
            for name in names:
                assert name in parsers, f"docs/flags.md names a command {name!r} that does not exist"
                missing = [f for f in flags if f not in parsers[name]._option_string_actions]
                assert not missing, f"docs/flags.md: {name} has no {missing}"
