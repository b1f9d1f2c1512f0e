from dataclasses import dataclass, field

import pytest
import yaml

from fdnet.config import from_dict, load_yaml, parse_overrides, replace_dotted, to_dict
from fdnet.errors import ConfigError


@dataclass
class Inner:
    size: tuple[int, int] = (32, 64)
    rate: float = 1e-4


@dataclass
class Outer:
    name: str = "x"
    frames: str = ""
    steps: int = 10
    flag: bool = False
    inner: Inner = field(default_factory=Inner)


def test_yaml_round_trip(tmp_path):
    config = Outer(name="run", steps=5, inner=Inner(size=(16, 32)))
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(to_dict(config), sort_keys=False))
    assert load_yaml(Outer, tmp_path / "c.yaml") == config


def test_overrides_are_typed_and_text_stays_text():
    config = replace_dotted(
        Outer(), parse_overrides(["steps=7", "inner.size=[8, 16]", "flag=true", "frames=0:37", "inner.rate=3e-4"])
    )
    assert config.steps == 7 and config.inner.size == (8, 16) and config.flag is True
    assert config.frames == "0:37"  # not YAML's base-60 reading (2265)
    assert config.inner.rate == pytest.approx(3e-4)


def test_bad_settings_are_named():
    with pytest.raises(ConfigError, match="unknown setting"):
        replace_dotted(Outer(), {"inner.nope": "1"})
    with pytest.raises(ConfigError, match="steps"):
        from_dict(Outer, {"steps": "many"})
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        parse_overrides(["steps"])
    assert to_dict(Outer())["inner"]["size"] == [32, 64]


@pytest.mark.parametrize(
    "setting, value, match",
    [
        ("steps", [7], r"config.steps: expected a number, got \[7\]"),
        ("inner.size", [[8], [16]], r"size: expected a number, got \[8\]"),
        ("inner.rate", {"a": 1}, "rate: expected a number"),
        ("name", ["a"], r"name: expected text, got \['a'\]"),
    ],
)
def test_nested_values_where_numbers_or_text_belong_are_named_errors(setting, value, match):
    with pytest.raises(ConfigError, match=match):
        replace_dotted(Outer(), {setting: value})


def _alias_bomb(levels: int = 6) -> str:
    """``data: {conditions: ...}`` of nested aliases: ~350 bytes that expand to 10^(levels+1)
    items (a message echoing them: ~50 MB; two levels more exhaust the memory)."""
    value = "&a0 [x, x, x, x, x, x, x, x, x, x]"
    for level in range(1, levels + 1):
        value = f"&a{level} [{value}" + f", *a{level - 1}" * 9 + "]"
    return f"data:\n  conditions: {value}\n"


def test_a_yaml_alias_bomb_in_a_config_is_refused_in_one_short_line(tmp_path, capsys):
    from fdnet.cli import main

    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(_alias_bomb())
    assert len(bomb.read_bytes()) < 400
    assert (
        main(
            [
                "train",
                "--data",
                str(tmp_path),
                "--preset",
                "tiny",
                "--out",
                str(tmp_path / "run"),
                "--config",
                str(bomb),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith(f"fdnet train: error: {bomb}: not valid YAML (line 2, column ")
    assert "aliases are not allowed" in err and len(err) < 400 and err.count("\n") == 1


def test_a_yaml_alias_bomb_in_a_runs_config_is_refused(tmp_path, capsys):
    from PIL import Image

    from fdnet import runs
    from fdnet.cli import main
    from tests.cli.test_extract import _tiny_run

    run = _tiny_run(tmp_path / "run")
    config = runs.latest_checkpoint(run) / runs.CONFIG_FILE
    stamp = config.read_text().splitlines()[0]  # the save it belongs to, so the checkpoint stays complete
    config.write_text(stamp + "\n" + _alias_bomb())
    images = tmp_path / "images"
    images.mkdir()
    Image.new("RGB", (64, 32)).save(images / "0.png")
    assert main(["extract", "--checkpoint", str(run), "--images", str(images), "--out", str(tmp_path / "v.npz")]) == 2
    err = capsys.readouterr().err
    assert "aliases are not allowed" in err and len(err) < 600 and err.count("\n") == 1


def test_a_wrong_value_is_shown_shortened():
    huge = [["x"] * 1000] * 1000  # what an alias bomb expands to, without the bomb
    with pytest.raises(ConfigError) as caught:
        replace_dotted(Outer(), {"name": huge})
    assert len(str(caught.value)) < 400 and "..." in str(caught.value)


def test_a_settings_file_over_a_mebibyte_is_refused_before_parsing(tmp_path):
    from fdnet.config import MAX_YAML_BYTES

    big = tmp_path / "big.yaml"
    big.write_text("name: x\n" + "# padding\n" * (MAX_YAML_BYTES // 10 + 1))
    with pytest.raises(ConfigError, match=r"big.yaml: \d+ bytes, too large for a config file \(at most 1024 KiB\)"):
        load_yaml(Outer, big)


@pytest.mark.parametrize(
    "value, message",
    [("[1,", "override steps: '\\[1,' is not a valid YAML value"), ("&a [*a]", "found an alias \\(\\*a\\)")],
)
def test_an_override_that_is_not_yaml_or_holds_an_alias_is_a_config_error(value, message):
    with pytest.raises(ConfigError, match=message):
        replace_dotted(Outer(), {"steps": value})


def test_a_file_nested_thousands_deep_is_refused_not_a_recursion_error(tmp_path):
    from fdnet.config import MAX_NESTING, check_nesting, load_json_text, read_yaml_file

    deep = tmp_path / "deep.yaml"
    deep.write_text("a: " + "[" * 2000 + "]" * 2000 + "\n")
    with pytest.raises(ConfigError, match="nested deeper than"):
        read_yaml_file(deep, "calibration file")
    shallow = tmp_path / "ok.yaml"
    shallow.write_text("a: " + "[" * (MAX_NESTING - 2) + "]" * (MAX_NESTING - 2) + "\n")
    assert read_yaml_file(shallow) is not None
    with pytest.raises(ConfigError, match="x.json: nested deeper than"):
        load_json_text("[" * 3000 + "]" * 3000, "x.json")
    check_nesting({"a": [{"b": 1}]}, "fine")
