"""Training presets: each builds a valid model; the CPU presets are what the docs say they are."""

import pytest

from fdnet.errors import ConfigError
from fdnet.methods.fdnet.model import FDNet
from fdnet.methods.fdnet.config import PRESETS, preset, validate


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_is_valid_and_builds(name):
    config = preset(name)
    validate(config)
    assert config.preset == name
    if name != "paper":  # the paper preset's 224x224 model is large; its sizes are checked by validate
        FDNet(config.model)


def test_cpu_preset_reads_a_frozen_trunk_and_cpu_scratch_reads_pixels():
    assert preset("cpu").model.backbone == "efficientnet-lite0"
    assert preset("cpu-scratch").model.backbone == "none"
    assert preset("paper").model.backbone == "none"


def test_unknown_preset_names_the_choices():
    with pytest.raises(ConfigError, match="cpu-scratch"):
        preset("fast")
