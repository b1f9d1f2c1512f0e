"""Training presets: each builds a valid model; the CPU presets are what the docs say they are."""

import pytest

from fdnet.errors import ConfigError
from fdnet.methods.fdnet.config import PRESETS, preset, validate
from fdnet.methods.fdnet.model import FDNet


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


def test_paper_preset_is_the_paper():
    config = preset("paper")
    assert config.model.critic_input == "raw"  # D_a reads v_c (section 3.3)
    assert config.loss.reconstruction_reduction == "sum"  # eq. 3
    assert (config.loss.reconstruction_weight, config.loss.appearance_weight, config.loss.adversarial_weight) == (
        1.0,
        1.0,
        1.0,
    )  # eq. 10
    assert config.schedule.one_batch_per_step  # Algorithm 1
    assert (
        config.schedule.pretrain_autoencoder_steps,
        config.schedule.pretrain_critic_steps,
        config.schedule.joint_steps,
        config.schedule.critic_updates_per_step,
    ) == (5000, 8000, 60000, 2)
    assert (config.optim.lr, config.optim.beta1, config.data.batch_per_domain) == (1e-4, 0.5, 4)
    assert tuple(config.model.input_size) == (224, 224) and config.model.vector_length == 512
    assert config.loss.triplet_margin == 0.1 and config.loss.triplet_vectors == "raw"


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_takes_a_gpu_when_there_is_one(name):
    assert preset(name).runtime.device == "auto"


@pytest.mark.parametrize(
    "setting, value", [("loss.reconstruction_reduction", "total"), ("loss.triplet_vectors", "unit")]
)
def test_bad_loss_choices_are_config_errors(setting, value):
    from fdnet.config import replace_dotted

    with pytest.raises(ConfigError, match=setting):
        validate(replace_dotted(preset("tiny"), {setting: value}))
