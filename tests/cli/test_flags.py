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
