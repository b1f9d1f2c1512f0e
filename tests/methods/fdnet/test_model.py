"""FDNet architecture: shapes (square and 2:1 inputs), parameter independence, init, bad sizes."""

import pytest
import torch

from fdnet.errors import ConfigError
from fdnet.methods.fdnet.model import FDNet, FDNetConfig, validate_architecture


@pytest.mark.parametrize("size", [(16, 32), (32, 16), (16, 16)])
def test_shapes_square_and_non_square(size):
    model = FDNet(FDNetConfig(input_size=size, widths=(4, 8), vector_length=12, critic_hidden=8)).eval()
    x = torch.rand(3, 3, *size)
    v_c, v_a = model.content(x), model.appearance(x)
    assert v_c.shape == (3, 12) and v_a.shape == (3, 12)
    out = model.decoder(v_c, v_a)
    assert out.shape == (3, 3, *size)
    assert model.discriminator(v_c, v_a).shape == (3,)


def test_nordland_cpu_layout_64x32():
    model = FDNet(FDNetConfig(input_size=(32, 64), widths=(4, 8, 8, 8), vector_length=16, critic_hidden=8))
    assert model.content_encoder.feature_shape == (8, 2, 4)
    assert model.decoder(torch.zeros(2, 16), torch.zeros(2, 16)).shape == (2, 3, 32, 64)


def test_encoders_do_not_share_weights():
    model = FDNet(FDNetConfig(input_size=(16, 16), widths=(4,), vector_length=4, critic_hidden=4))
    c = dict(model.content_encoder.named_parameters())
    a = dict(model.appearance_encoder.named_parameters())
    assert c.keys() == a.keys()
    assert all(c[k].data_ptr() != a[k].data_ptr() for k in c)
    assert not torch.equal(c["fc.weight"], a["fc.weight"])


def test_init_is_normal_0_002():
    torch.manual_seed(0)
    model = FDNet(FDNetConfig(input_size=(32, 32), widths=(16, 32), vector_length=64, critic_hidden=64))
    w = model.content_encoder.fc.weight
    assert abs(float(w.mean())) < 2e-3 and abs(float(w.std()) - 0.02) < 2e-3


def test_outputs_tanh_or_linear():
    tanh = FDNet(FDNetConfig(input_size=(8, 8), widths=(4,), vector_length=4, critic_hidden=4))
    assert isinstance(tanh.decoder.blocks[-1][-1], torch.nn.Tanh)
    lin = FDNet(FDNetConfig(input_size=(8, 8), widths=(4,), vector_length=4, critic_hidden=4, input_norm="per_image"))
    assert isinstance(lin.decoder.blocks[-1][-1], torch.nn.ConvTranspose2d)
    x = torch.rand(2, 3, 8, 8)
    z = lin.preprocess(x)
    assert torch.allclose(z.mean(dim=(1, 2, 3)), torch.zeros(2), atol=1e-5)


@pytest.mark.parametrize(
    "size, widths, match",
    [
        ((30, 64), (8, 8), "height 30"),
        ((32, 60), (8, 8, 8), "width 60"),
        ((8, 8), (4, 4, 4, 4), "multiple of 2\\^4 = 16"),
    ],
)
def test_impossible_input_size_is_a_config_error(size, widths, match):
    with pytest.raises(ConfigError, match=match):
        validate_architecture(FDNetConfig(input_size=size, widths=widths))
    with pytest.raises(ConfigError):
        FDNet(FDNetConfig(input_size=size, widths=widths))


def test_unknown_options_are_config_errors():
    with pytest.raises(ConfigError, match="input_norm"):
        validate_architecture(FDNetConfig(input_size=(16, 16), widths=(4,), input_norm="zca"))
    with pytest.raises(ConfigError, match="critic_input"):
        validate_architecture(FDNetConfig(input_size=(16, 16), widths=(4,), critic_input="cosine"))


TRUNK_HEAD = dict(
    input_size=(128, 256), widths=(16,), backbone="efficientnet-lite0", backbone_block=7, content_head="trunk_residual"
)


@pytest.mark.parametrize(
    "settings, match",
    [
        (dict(backbone="none", content_head="encoder", backbone_block_candidates=(7, 14)), "needs model.backbone"),
        (dict(content_head="encoder", backbone_block_candidates=(7, 14)), "trunk_residual"),
        (dict(backbone_block_candidates=(10, 14)), r"backbone_block=7 is not among .*\[10, 14\]"),
        (dict(backbone_block_candidates=(7, 7)), "names a block twice"),
        (dict(backbone_block_candidates=(7, 16)), "block 16: backbone block 16 does not exist"),
        (dict(input_size=(96, 192), backbone_block_candidates=(7, 14)), "block 14: model.input_size: height 96"),
        (dict(backbone_block_candidates=(0, 7)), "block 0: model: this architecture's largest layer would have"),
    ],
)
def test_bad_trunk_block_candidates_are_config_errors(settings, match):
    with pytest.raises(ConfigError, match=match):
        validate_architecture(FDNetConfig(**{**TRUNK_HEAD, **settings}))


def test_trunk_block_candidates_that_fit_are_valid():
    validate_architecture(FDNetConfig(**TRUNK_HEAD, backbone_block_candidates=(7, 14)))


def test_a_model_whose_largest_layer_would_not_fit_is_refused_before_building():
    # block 0 at 128x256: a 131072-long flattened map feeding the decoder's first layer
    with pytest.raises(ConfigError, match=r"largest layer would have 4\.31e\+09 weights .*deeper model.backbone_block"):
        validate_architecture(FDNetConfig(**{**TRUNK_HEAD, "backbone_block": 0}))


@pytest.mark.parametrize("name", ["cpu", "cpu-scratch", "tiny"])
def test_the_largest_layer_estimate_is_the_built_models(name):
    from fdnet.methods.fdnet.config import preset
    from fdnet.methods.fdnet.model import MAX_LAYER_WEIGHTS, largest_layer_weights

    config = preset(name).model
    model = FDNet(config)
    built = max(m.weight.numel() for m in model.modules() if isinstance(m, torch.nn.Linear))
    assert largest_layer_weights(config) == built
    assert built < MAX_LAYER_WEIGHTS / 4  # the presets fit with room to spare


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(vector_length=10241), r"L = 10241 is longer than the trunk map it projects \(10240 values at block 7"),
        (dict(projection_init="whiten"), "model.projection_init: 'whiten'"),
        (dict(projection_pca_power=2.0), "projection_pca_power must lie in"),
        (dict(pair_sequence_length=0), "pair_sequence_length must be >= 1"),
        (dict(backbone="none", backbone_block_candidates=()), "trunk_projection needs a model.backbone"),
    ],
)
def test_projection_head_settings_it_cannot_take_are_refused(change, message):
    config = FDNetConfig(**{**TRUNK_HEAD, "content_head": "trunk_projection", **change})
    with pytest.raises(ConfigError, match=message):
        validate_architecture(config)


def test_projection_head_vector_has_the_paper_length():
    model = FDNet(FDNetConfig(**{**TRUNK_HEAD, "content_head": "trunk_projection", "vector_length": 512})).eval()
    assert model.content_length == 512
    assert sum(p.numel() for p in model.content_encoder.parameters()) == 512 * 512  # only R trains
    with torch.no_grad():
        assert model.content(torch.rand(2, 3, 128, 256)).shape == (2, 512)


@pytest.mark.parametrize(
    "backbone, block, channels", [("efficientnet-lite1", 12, 112), ("efficientnet-lite2", 12, 120)]
)
def test_a_larger_lite_trunk_sets_the_map_fdnet_reads(backbone, block, channels):
    from fdnet.methods.fdnet.trunk import FrozenTrunk

    config = FDNetConfig(
        **{**TRUNK_HEAD, "input_size": (64, 128), "backbone": backbone, "backbone_block": block, "vector_length": 16}
    )
    validate_architecture(config)
    assert config.encoder_input_size() == (4, 8)  # stride 16, as Lite0's block 7
    model = FDNet(config).eval()
    assert model.trunk.backbone == backbone and model.trunk.channels == channels
    images = torch.rand(2, 3, 64, 128)
    with torch.no_grad():
        assert torch.equal(model.trunk(images), FrozenTrunk(block, backbone)(images))
        assert model.content(images).shape == (2, channels * 4 * 8)  # the residual head keeps the map's length
    with pytest.raises(ConfigError, match="backbone block 21 does not exist"):
        validate_architecture(FDNetConfig(**{**TRUNK_HEAD, "backbone": backbone, "backbone_block": 21}))
