"""The pretrained EfficientNet-Lite0 trunk: real ImageNet weights, shapes, bf16 closeness."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fdnet import backbones as backbone
from fdnet.errors import ConfigError


def _cos(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a.reshape(len(a), -1)
    b = b.reshape(len(b), -1)
    return np.sum(a * b, 1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))


def test_pretrained_weights_are_loaded_not_random():
    import torch

    model = backbone.pretrained_model()
    assert backbone.pretrained_model() is model  # cached per process
    fresh = backbone.build_efficientnet_lite0(pretrained=False)
    # every parameter tensor of the pretrained model differs from a random initialisation
    w_pre = model._conv_stem.weight
    w_rand = fresh._conv_stem.weight
    assert not torch.allclose(w_pre, w_rand)
    assert not model.training
    assert not any(p.requires_grad for p in model.parameters())


def test_maps_have_documented_shape_and_stride(rng):
    images = rng.random((2, 64, 96, 3), dtype=np.float32)
    for block in (4, backbone.CONV3_LIKE_BLOCK, 15):
        fe = backbone.FeatureExtractor(block=block, bf16=False)
        maps = fe.features(images)
        assert maps.dtype == np.float32
        assert maps.shape == (2, fe.channels, *fe.map_size((64, 96)))
    assert backbone.FeatureExtractor(bf16=False).map_size((224, 224)) == (14, 14)


def test_bf16_maps_stay_close_to_float32(rng):
    images = rng.random((2, 96, 96, 3), dtype=np.float32)
    exact = backbone.FeatureExtractor(bf16=False).features(images)
    fast = backbone.FeatureExtractor(bf16=True).features(images)
    assert fast.dtype == np.float32
    assert _cos(exact, fast).min() > 0.98


def test_deterministic_and_batch_independent(rng):
    images = rng.random((3, 64, 64, 3), dtype=np.float32)
    fe = backbone.FeatureExtractor(bf16=False)
    whole = fe.features(images)
    np.testing.assert_allclose(fe.features(images), whole)
    np.testing.assert_allclose(fe.features(images[1:2])[0], whole[1], rtol=1e-4, atol=1e-4)


def test_pretrained_features_separate_real_places():
    """ImageNet features of the same place (left vs right camera) are more alike than of
    places 60 frames apart: the weights carry real visual knowledge."""
    from fdnet.data.images import load_images

    from conftest import require_shared

    root = require_shared("gardens_point")
    left = load_images([root / "day_left" / f"Image{i:03d}.jpg" for i in (20, 80, 140)], (224, 224))
    right = load_images([root / "day_right" / f"Image{i:03d}.jpg" for i in (20, 80, 140)], (224, 224))
    fe = backbone.FeatureExtractor()
    a = fe.features(left).reshape(3, -1)
    b = fe.features(right).reshape(3, -1)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    sim = a @ b.T
    assert (np.argmax(sim, axis=1) == np.arange(3)).all()


def test_bad_block_is_a_config_error():
    with pytest.raises(ConfigError, match="blocks 0..15"):
        backbone.FeatureExtractor(block=16)


def test_threads_are_restored():
    import torch

    before = torch.get_num_threads()
    with backbone.torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before


# ------------------------------------------------------------------ every shipped EfficientNet-Lite
@pytest.mark.parametrize("name", backbone.BACKBONES)
def test_per_backbone_tables_match_the_built_models(name):
    """block_channels / block_stride (written out, so no model is loaded to know them) agree with
    each pretrained model run on a 64x96 input, block by block."""
    import torch

    model = backbone.pretrained_model(None, name)
    assert len(model._blocks) == backbone.num_blocks(name)
    with torch.inference_mode():
        x = model._swish(model._bn0(model._conv_stem(torch.zeros(1, 3, 64, 96))))
        for block, module in enumerate(model._blocks):
            x = module(x)
            assert x.shape[1] == backbone.block_channels(name, block), (name, block)
            assert (x.shape[2], x.shape[3]) == backbone.map_size((64, 96), block, name), (name, block)
            assert 64 // x.shape[2] == backbone.block_stride(name, block), (name, block)


def test_lite0_names_keep_working():
    for block in range(backbone.NUM_BLOCKS):
        assert backbone.block_channels(None, block) == backbone.BLOCK_CHANNELS[block]
        assert backbone.block_stride("efficientnet-lite0", block) == backbone.BLOCK_STRIDE[block]
    assert backbone.num_blocks() == backbone.NUM_BLOCKS == 16
    assert backbone.num_blocks("efficientnet-lite1") == backbone.num_blocks("efficientnet-lite2") == 21


def test_each_backbone_has_its_own_weights(rng):
    images = rng.random((1, 64, 64, 3), dtype=np.float32)
    lite1 = backbone.FeatureExtractor(block=10, backbone="efficientnet-lite1", bf16=False)
    lite2 = backbone.FeatureExtractor(block=10, backbone="efficientnet-lite2", bf16=False)
    assert lite1.features(images).shape == (1, 80, 4, 4) and lite2.features(images).shape == (1, 88, 4, 4)
    assert lite1.settings()["backbone"] == "efficientnet-lite1 (ImageNet)"
    assert backbone.pretrained_model(None, "efficientnet-lite1") is not backbone.pretrained_model()


def test_bad_backbone_or_block_names_the_choices():
    with pytest.raises(ConfigError, match="choose one of efficientnet-lite0, efficientnet-lite1, efficientnet-lite2"):
        backbone.check_backbone("efficientnet-lite4")
    with pytest.raises(ConfigError, match="efficientnet-lite1 has blocks 0..20"):
        backbone.block_channels("efficientnet-lite1", 21)


def test_cache_passes_split_by_the_widest_activation_and_keep_every_row():
    import torch

    conv = torch.nn.Conv2d(3, 8, 3, padding=1).eval()
    widest = 8 * 16 * 16 * 4  # one image's output, float32: the widest (and only) leaf's
    passes = backbone.CachePasses(cache_bytes=2 * widest * 3)
    sizes = []

    def forward(part):
        sizes.append(len(part))
        return conv(part)

    x = torch.rand(7, 3, 16, 16)
    with torch.inference_mode():
        whole = conv(x)
        assert passes.images_per_pass(conv, conv, x) == 3
        out = passes.run(conv, forward, x)
        assert sizes == [3, 3, 1]
        sizes.clear()
        padded = passes.run(conv, forward, x, pad=8)
        assert sizes == [3, 3, 3]  # a compiled graph's one batch size: the last pass filled up
        sizes.clear()
        passes.run(conv, forward, x[:5], pad=2)
        assert sizes == [2, 2, 2]  # never more than the graph's batch
    torch.testing.assert_close(out, whole)
    torch.testing.assert_close(padded, whole)
    assert not conv._forward_hooks  # the measuring hooks are gone
    # a cache smaller than one image: one image a pass, never none
    assert backbone.CachePasses(cache_bytes=1).images_per_pass(conv, conv, x) == 1
    assert backbone.last_level_cache_bytes() > 0


def test_trunk_maps_are_the_same_in_passes_as_in_one(rng):
    images = rng.integers(0, 256, (5, 64, 96, 3), dtype=np.uint8)
    fe = backbone.FeatureExtractor(bf16=False)
    fe._passes = backbone.CachePasses(cache_bytes=1 << 40)
    one = fe.features(images)
    fe._passes = backbone.CachePasses(cache_bytes=1)
    np.testing.assert_allclose(fe.features(images), one, rtol=1e-4, atol=1e-4)  # oneDNN: batch-size kernels


@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def test_bytes_become_the_float_path_s_values_to_the_bit_on_every_device(device):
    from fdnet.backbones import unit_from_bytes

    values = np.arange(256, dtype=np.uint8)
    got = unit_from_bytes(torch.from_numpy(values).to(device)).cpu().numpy()
    np.testing.assert_array_equal(got, values.astype(np.float32) / np.float32(255.0))
