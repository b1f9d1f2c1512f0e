"""The optional frozen ImageNet trunk in front of FDNet's encoders (models/trunk.py)."""

import re

import numpy as np
import pytest
import torch

from fdnet.config import replace_dotted
from fdnet.errors import ConfigError
from fdnet.methods.fdnet.config import preset
from fdnet.methods.fdnet.model import FDNet, FDNetConfig
from fdnet.methods.fdnet.training import FDNetTraining, load_training_images
from fdnet.methods.fdnet.trunk import FrozenTrunk, trunk_map_size
from fdnet.runs import load_weights
from fdnet.training.loop import Trainer
from tests.training.test_loop import make_dataset

# block 4: stride 8, 40 channels; a 32x64 image gives a 4x8 map, one FDNet block makes it 2x4
SMALL = dict(
    input_size=(32, 64),
    widths=(16,),
    vector_length=16,
    critic_hidden=16,
    backbone="efficientnet-lite0",
    backbone_block=4,
)


def test_map_size_and_channels():
    assert trunk_map_size((128, 256), 7) == (8, 16)
    assert trunk_map_size((30, 60), 4) == (4, 8)  # "same" padding rounds up
    model = FDNet(FDNetConfig(**SMALL))
    assert model.preprocess(torch.rand(2, 3, 32, 64)).shape == (2, 40, 4, 8)
    assert model.content(torch.rand(2, 3, 32, 64)).shape == (2, 16)


def test_trunk_stays_frozen_in_eval_mode_and_out_of_run_directories():
    model = FDNet(FDNetConfig(**SMALL))
    model.train()
    assert model.content_encoder.training and not model.trunk.training
    assert not any(p.requires_grad for p in model.trunk.parameters())
    saved = {t.data_ptr() for part in model.named_parts().values() for t in part.state_dict().values()}
    assert saved.isdisjoint(t.data_ptr() for t in model.trunk.state_dict().values())


def test_trunk_matches_the_pretrained_feature_extractor():
    from fdnet.backbones import FeatureExtractor

    images = np.random.default_rng(0).random((2, 32, 64, 3), dtype=np.float32)
    ours = FrozenTrunk(4)(torch.from_numpy(images).permute(0, 3, 1, 2))
    reference = FeatureExtractor(block=4, bf16=False).features(images)
    np.testing.assert_allclose(ours.numpy(), reference, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize(
    "overrides, message",
    [
        (dict(input_size=(40, 64)), "multiple of 8 x 2^1 = 16"),
        (dict(input_norm="per_patch"), "per_patch cannot be used"),
        (dict(backbone="resnet50"), "model.backbone"),
        (dict(backbone_block=16), "block 16 does not exist"),
    ],
)
def test_bad_backbone_settings_are_config_errors(overrides, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        FDNet(FDNetConfig(**{**SMALL, **overrides}))


def test_training_with_a_trunk_changes_the_encoders_but_not_the_trunk(tmp_path):
    make_dataset(tmp_path / "data", size=(32, 64))
    config = replace_dotted(
        preset("tiny"), {"data.root": str(tmp_path / "data"), **{f"model.{k}": v for k, v in SMALL.items()}}
    )
    method = FDNetTraining(config, load_training_images(config))
    trainer = Trainer(method, tmp_path / "run", tensorboard=False)
    trainer.model = method.model
    trunk_before = {k: v.clone() for k, v in trainer.model.trunk.state_dict().items()}
    encoder_before = {k: v.clone() for k, v in trainer.model.content_encoder.state_dict().items()}
    trainer.fit(progress=False)
    for key, value in trainer.model.trunk.state_dict().items():
        assert torch.equal(value, trunk_before[key]), key
    assert any(not torch.equal(v, encoder_before[k]) for k, v in trainer.model.content_encoder.state_dict().items())
    # the run directory rebuilds the same descriptor (trunk from the package, parts from the run)
    fresh = FDNet(config.model)
    load_weights(tmp_path / "run", fresh.named_parts())
    x = torch.rand(3, 3, 32, 64)
    trainer.model.eval(), fresh.eval()
    torch.testing.assert_close(trainer.model.content(x), fresh.content(x))


RESIDUAL = {**SMALL, "content_head": "trunk_residual", "residual_rank": 4}


def test_residual_content_head_starts_exactly_at_the_centred_trunk_descriptor():
    model = FDNet(FDNetConfig(**RESIDUAL)).eval()
    images = torch.rand(5, 3, 32, 64)
    maps = model.preprocess(images)
    model.content_encoder.set_mean(maps)
    expected = maps.flatten(1) - maps.flatten(1).mean(0)
    torch.testing.assert_close(model.content(images), expected)
    assert model.content_length == maps[0].numel()
    # the discriminator and decoder take the longer content vector
    assert model.discriminator.net[0].in_features == 2 * model.content_length


def test_residual_content_head_needs_a_trunk_and_a_positive_rank():
    with pytest.raises(ConfigError, match="needs a model.backbone"):
        FDNet(FDNetConfig(input_size=(32, 64), widths=(8, 16), content_head="trunk_residual"))
    with pytest.raises(ConfigError, match="residual_rank"):
        FDNet(FDNetConfig(**{**RESIDUAL, "residual_rank": 0}))
    with pytest.raises(ConfigError, match="content_head"):
        FDNet(FDNetConfig(**{**RESIDUAL, "content_head": "mlp"}))


def test_training_the_residual_head_moves_only_its_low_rank_part_and_keeps_the_mean(tmp_path):
    from fdnet.methods.fdnet.descriptor import FDNetDescriptor

    make_dataset(tmp_path / "data", size=(32, 64))
    config = replace_dotted(
        preset("tiny"), {"data.root": str(tmp_path / "data"), **{f"model.{k}": v for k, v in RESIDUAL.items()}}
    )
    method = FDNetTraining(config, load_training_images(config))
    trainer = Trainer(method, tmp_path / "run", tensorboard=False)
    head = method.model.content_encoder
    assert float(head.mean.abs().sum()) > 0, "start() sets the mean of the training maps"
    trainer.fit(progress=False)
    assert float(head.u.abs().sum()) > 0, "the adversarial/reconstruction gradient reached U"
    descriptor = FDNetDescriptor(checkpoint=tmp_path / "run")
    assert descriptor.dim == head.vector_length
    torch.testing.assert_close(descriptor.model.content_encoder.mean, head.mean)


def test_condition_means_init_removes_the_direction_between_the_conditions():
    torch.manual_seed(0)
    model = FDNet(FDNetConfig(**{**RESIDUAL, "residual_init": "condition_means"})).eval()
    a, b = torch.rand(6, 3, 32, 64), torch.rand(6, 3, 32, 64) * 0.5
    maps = [model.preprocess(a), model.preprocess(b)]
    model.content_encoder.set_mean(torch.cat(maps))
    assert model.content_encoder.remove_condition_means(maps) == 1
    content = [model.content(a), model.content(b)]
    # after removal the two conditions' mean content vectors coincide
    torch.testing.assert_close(content[0].mean(0), content[1].mean(0), atol=1e-4, rtol=0)
    with pytest.raises(ConfigError, match="residual_init"):
        FDNet(FDNetConfig(**{**RESIDUAL, "residual_init": "pca"}))


def test_a_lite2_trunk_matches_its_feature_extractor():
    from fdnet.backbones import FeatureExtractor

    images = np.random.default_rng(0).random((2, 32, 64, 3), dtype=np.float32)
    trunk = FrozenTrunk(12, backbone="efficientnet-lite2")
    assert trunk.channels == 120 and trunk_map_size((32, 64), 12, "efficientnet-lite2") == (2, 4)
    ours = trunk(torch.from_numpy(images).permute(0, 3, 1, 2))
    reference = FeatureExtractor(block=12, backbone="efficientnet-lite2", bf16=False).features(images)
    np.testing.assert_allclose(ours.numpy(), reference, rtol=1e-4, atol=1e-4)
