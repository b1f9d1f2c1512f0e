"""Settings every trained method shares: the validation pair."""

import pytest

from fdnet.errors import ConfigError
from fdnet.methods.settings import ValidationConfig, check_validation_pair


@pytest.mark.parametrize("reference, query, match", [
    ("day", "", "give both a reference and a query"),
    ("", "night", "give both a reference and a query"),
    ("day", "day", r"the same condition \('day'\).*choose two conditions"),
])
def test_a_validation_pair_needs_two_different_conditions(reference, query, match):
    with pytest.raises(ConfigError, match=match):
        check_validation_pair(ValidationConfig(reference=reference, query=query))


def test_two_conditions_or_none_are_a_validation_pair():
    check_validation_pair(ValidationConfig(reference="day", query="night"))
    check_validation_pair(ValidationConfig())


def test_runs_written_before_the_shared_sections_read_in_the_current_layout(tmp_path):
    """CALC/NetVLAD runs once kept lr, seed, bf16, checkpoint_every ... under ``train``; their
    config.yaml still loads (optim.* and runtime.* now, as for every method)."""
    import yaml

    from fdnet.config import load_yaml, to_dict
    from fdnet.methods.calc.config import CALCRunConfig
    from fdnet.methods.netvlad.config import NetVLADRunConfig

    for cls in (CALCRunConfig, NetVLADRunConfig):
        old = to_dict(cls())
        old["train"].update({"optimizer": "sgd", "lr": 9e-4, "seed": 3, "bf16": False, "checkpoint_every": 7,
                             "log_every": 5, "momentum": 0.8, "weight_decay": 0.01})
        del old["optim"], old["runtime"], old["preset"]
        path = tmp_path / f"{cls.__name__}.yaml"
        path.write_text(yaml.safe_dump(old))
        config = load_yaml(cls, path)
        assert (config.optim.optimizer, config.optim.lr, config.optim.momentum) == ("sgd", 9e-4, 0.8)
        assert (config.runtime.seed, config.runtime.checkpoint_every, config.runtime.log_every) == (3, 7, 5)
        assert config.runtime.device == "auto" and config.preset == ""
