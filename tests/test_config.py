from dataclasses import dataclass, field

import pytest

from fdnet.config import from_dict, load_yaml, parse_overrides, replace_dotted, save_yaml, to_dict
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
    save_yaml(config, tmp_path / "c.yaml")
    assert load_yaml(Outer, tmp_path / "c.yaml") == config


def test_overrides_are_typed_and_text_stays_text():
    config = replace_dotted(Outer(), parse_overrides(["steps=7", "inner.size=[8, 16]", "flag=true",
                                                      "frames=0:37", "inner.rate=3e-4"]))
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


@pytest.mark.parametrize("setting, value, match", [
    ("steps", [7], r"config.steps: expected a number, got \[7\]"),
    ("inner.size", [[8], [16]], r"size: expected a number, got \[8\]"),
    ("inner.rate", {"a": 1}, "rate: expected a number"),
    ("name", ["a"], r"name: expected text, got \['a'\]"),
])
def test_nested_values_where_numbers_or_text_belong_are_named_errors(setting, value, match):
    with pytest.raises(ConfigError, match=match):
        replace_dotted(Outer(), {setting: value})
