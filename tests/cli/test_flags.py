"""Old flag spellings still work as the new ones, with a one-line note on standard error."""

import argparse

import pytest

from fdnet.cli import build_parser, main
from fdnet.cli.flags import add_old_spelling, note_old_spellings
from fdnet.errors import ConfigError


def test_an_old_spelling_sets_the_same_setting_and_is_noted(caplog):
    p = argparse.ArgumentParser()
    p.add_argument("--num-frames", type=int, default=400)
    p.add_argument("--format-set", action="append", default=[])
    p.add_argument("--db", required=True)
    add_old_spelling(p, "--frames", "--num-frames")
    add_old_spelling(p, "--set", "--format-set")
    add_old_spelling(p, "--out", "--db")
    args = p.parse_args(["--frames", "40", "--set", "a=1", "--format-set", "b=2", "--out", "map.db"])
    assert (args.num_frames, args.format_set, args.db) == (40, ["a=1", "b=2"], "map.db")
    with caplog.at_level("WARNING"):
        note_old_spellings(args)
    assert [r.getMessage().split(" is ")[0] for r in caplog.records] == ["--frames", "--set", "--out"]
    new = p.parse_args(["--db", "map.db"])
    assert new.num_frames == 400
    note_old_spellings(new)  # nothing to say, nothing missing
    with pytest.raises(ConfigError, match="required: --db"):
        note_old_spellings(p.parse_args([]))


@pytest.mark.parametrize("command,old,new", [
    (["synth"], "--frames", "--num-frames"),
    (["demo"], "--train-minutes", "--max-minutes"),
    (["groundtruth"], "--dataset", "--data"),
    (["groundtruth"], "--tolerance-frames", "--tolerance"),
    (["groundtruth"], "--set", "--format-set"),
    (["database", "build"], "--out", "--db"),
    (["benchmark"], "--methods", "--method"),
    (["reproduce"], "--methods", "--method"),
    (["evaluate"], "--methods", "--method"),
])
def test_every_renamed_flag_keeps_its_old_spelling(command, old, new):
    parser = build_parser()
    sub = parser._subparsers._group_actions[0].choices[command[0]]
    if len(command) > 1:
        sub = sub._subparsers._group_actions[0].choices[command[1]]
    assert sub._option_string_actions[old].dest == sub._option_string_actions[new].dest


def test_a_command_with_an_old_spelling_runs_and_says_so(tmp_path, capsys):
    assert main(["synth", "--out", str(tmp_path / "route"), "--frames", "3", "--conditions", "summer"]) == 0
    captured = capsys.readouterr()
    assert len(list((tmp_path / "route" / "summer").iterdir())) == 3
    assert captured.err.startswith("fdnet synth: warning: --frames is the old spelling of --num-frames")
    assert main(["synth", "--out", str(tmp_path / "route"), "--num-frames", "2", "--conditions", "summer"]) == 0
    assert "old spelling" not in capsys.readouterr().err


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
        start = lines.index("| flag | meaning | commands | old spellings |")
        end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
        return [line for line in lines[start:end] if line.startswith("| `--")]

    root = Path(__file__).resolve().parents[2]
    tables = [flag_table((root / name).read_text()) for name in ("docs/flags.md", "docs/guide.md")]
    assert tables[0] == tables[1], "docs/guide.md's flag table differs from docs/flags.md's"
    rows = [line.split(" | ") for line in tables[0]]
    assert len(rows) >= 20
    return rows


def test_the_flag_table_matches_the_parsers():
    import re

    parsers = _leaf_parsers()
    checked_old = 0
    for flag_cell, _, commands, old in _table_rows():
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
        for spelling, where in re.findall(r"`(--[a-z-]+)[^`]*` \(([^)]*)\)", old):
            targets = [c.strip() for c in where.split(",")]
            if targets == ["every command with `--method`"]:
                targets = [n for n, p in parsers.items() if "--method" in p._option_string_actions]
            for name in targets:
                actions = parsers[name]._option_string_actions
                assert spelling in actions, f"{name}: old spelling {spelling} is not accepted"
                assert actions[spelling].dest == actions[flags[0]].dest, f"{name}: {spelling} is not {flags[0]}"
                checked_old += 1
    assert checked_old >= 15, checked_old  # the table's old spellings were read
