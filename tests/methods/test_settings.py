"""Settings every trained method shares: the validation pair."""

import pytest

from fdnet.errors import ConfigError
from fdnet.methods.settings import ValidationConfig, check_validation_pair


@pytest.mark.parametrize(
    "reference, query, match",
    [
        ("day", "", "give both a reference and a query"),
        ("", "night", "give both a reference and a query"),
        ("day", "day", r"the same condition \('day'\).*choose two conditions"),
    ],
)
def test_a_validation_pair_needs_two_different_conditions(reference, query, match):
    with pytest.raises(ConfigError, match=match):
        check_validation_pair(ValidationConfig(reference=reference, query=query))


def test_two_conditions_or_none_are_a_validation_pair():
    check_validation_pair(ValidationConfig(reference="day", query="night"))
    check_validation_pair(ValidationConfig())


def test_a_shared_setting_under_train_is_an_unknown_setting(tmp_path):
    """lr, seed, bf16, checkpoint_every ... live in ``optim`` and ``runtime`` for every method; a
    CALC/NetVLAD config.yaml with one of them under ``train`` is refused naming it."""
    import yaml

    from fdnet.config import load_yaml, to_dict
    from fdnet.methods.calc.config import CALCRunConfig
    from fdnet.methods.netvlad.config import NetVLADRunConfig

    for cls in (CALCRunConfig, NetVLADRunConfig):
        data = to_dict(cls())
        data["train"]["lr"] = 9e-4
        path = tmp_path / f"{cls.__name__}.yaml"
        path.write_text(yaml.safe_dump(data))
        with pytest.raises(ConfigError, match=r"unknown setting\(s\) lr"):
            load_yaml(cls, path)
