"""HybridNet conv4: only with the user's converted weights, never a substitute."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.descriptors.alexnet import build_caffenet_features
from fdnet.descriptors.registry import create
from fdnet.errors import ConfigError, NotAvailableError


def test_without_weights_it_is_not_available_and_says_how_to_supply_them(tmp_path):
    with pytest.raises(NotAvailableError, match="safetensors.*--weights FILE"):
        create("hybridnet")
    with pytest.raises(NotAvailableError, match="not found"):
        create("hybridnet", weights=str(tmp_path / "HybridNet.safetensors"))


def _caffenet_file(tmp_path):
    import torch
    from safetensors.torch import save_file

    torch.manual_seed(0)
    convs = build_caffenet_features()
    path = tmp_path / "hybridnet.safetensors"
    save_file({k: v.contiguous() for k, v in convs.state_dict().items()}, str(path))
    return path


def test_user_weights_give_conv4_of_caffenet_layout(tmp_path, rng):
    path = _caffenet_file(tmp_path)
    d = create("hybridnet", weights=str(path))
    assert d.input_size == (227, 227)
    assert d.settings()["feature_map"] == [384, 13, 13]
    images = rng.random((2, 227, 227, 3), dtype=np.float32)
    v = d.describe(images)
    assert v.shape == (2, 64896) and v.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, rtol=1e-5)
    np.testing.assert_array_equal(d.describe(images), v)
    projected = create("hybridnet", weights=str(path), dim=512)
    assert projected.describe(images).shape == (2, 512)


def test_hybridnet_vectors_are_the_same_in_passes_as_in_one(tmp_path, rng):
    from fdnet.backbones import CachePasses

    d = create("hybridnet", weights=str(_caffenet_file(tmp_path)))
    images = rng.integers(0, 256, (3, 227, 227, 3), dtype=np.uint8)
    d.trunk._passes = CachePasses(cache_bytes=1 << 40)
    one = d.describe(images)
    d.trunk._passes = CachePasses(cache_bytes=1)  # one image a pass
    np.testing.assert_allclose(d.describe(images), one, atol=1e-6)


def test_wrong_shapes_are_config_errors(tmp_path):
    import torch
    from safetensors.torch import save_file

    convs = build_caffenet_features()
    state = {k: v.contiguous() for k, v in convs.state_dict().items()}
    state["conv4.weight"] = torch.zeros(384, 384, 3, 3)  # ungrouped: not CaffeNet's shape
    path = tmp_path / "bad.safetensors"
    save_file(state, str(path))
    with pytest.raises(ConfigError, match="conv4.weight has shape"):
        create("hybridnet", weights=str(path))
