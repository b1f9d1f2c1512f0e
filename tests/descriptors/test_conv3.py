"""Conv3 + Gaussian random projection (Sünderhauf et al. IROS 2015)."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.descriptors.alexnet import build_alexnet_features
from fdnet.descriptors.conv3 import Conv3Descriptor, gaussian_random_projection
from fdnet.errors import ConfigError, NotAvailableError

from conftest import require_shared


def test_projection_is_seeded_and_jl_scaled():
    a = gaussian_random_projection(1000, 64, seed=3)
    np.testing.assert_array_equal(a, gaussian_random_projection(1000, 64, seed=3))
    assert not np.array_equal(a, gaussian_random_projection(1000, 64, seed=4))
    assert a.dtype == np.float32
    assert a.std() == pytest.approx(1 / np.sqrt(64), rel=0.05)


def test_shape_norm_determinism_and_same_projection_across_instances(rng):
    images = rng.random((2, 96, 128, 3), dtype=np.float32)
    d = Conv3Descriptor(input_size=(96, 128), bf16=False)
    v = d.describe(images)
    assert v.shape == (2, 512) and v.dtype == np.float32 and d.dim == 512
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, rtol=1e-5)
    # a second instance (e.g. another process describing the queries) projects identically
    np.testing.assert_allclose(
        Conv3Descriptor(input_size=(96, 128), bf16=False).describe(images), v, rtol=1e-5, atol=1e-6
    )
    assert d.settings()["feature_map"] == [80, 6, 8]
    raw = Conv3Descriptor(input_size=(96, 128), dim=0, bf16=False)
    assert raw.dim == 80 * 6 * 8


def test_user_alexnet_weights_give_paper_conv3_size(tmp_path, rng):
    import torch
    from safetensors.torch import save_file

    torch.manual_seed(0)
    features = build_alexnet_features()
    state = {f"features.{k}": v for k, v in features.state_dict().items()}
    state["classifier.1.weight"] = torch.zeros(2, 2)  # extra keys (the classifier) are ignored
    path = tmp_path / "alexnet.safetensors"
    save_file(state, str(path))
    d = Conv3Descriptor(weights=path, dim=0)
    assert d.input_size == (227, 227) and d.dim == 64896  # 384 x 13 x 13, as in the paper
    images = rng.random((1, 227, 227, 3), dtype=np.float32)
    v = d.describe(images)
    # it is really the user's conv3 (+ ReLU) that is described
    x = torch.from_numpy((images - [0.485, 0.456, 0.406]) / [0.229, 0.224, 0.225]).float().permute(0, 3, 1, 2)
    with torch.no_grad():
        expected = features[:8](x).reshape(1, -1).numpy()
    np.testing.assert_allclose(v, expected / np.linalg.norm(expected), rtol=1e-4, atol=1e-6)
    # the torch.save format works too
    torch.save(state, tmp_path / "alexnet.pth")
    assert Conv3Descriptor(weights=tmp_path / "alexnet.pth").dim == 512


def test_bad_weights_files_are_clear_errors(tmp_path):
    with pytest.raises(NotAvailableError, match="not found"):
        Conv3Descriptor(weights=tmp_path / "missing.pth")
    import torch
    from safetensors.torch import save_file

    wrong = tmp_path / "wrong.safetensors"
    save_file({"conv1.weight": torch.zeros(96, 3, 11, 11)}, str(wrong))
    with pytest.raises(ConfigError, match="missing features.0.weight"):
        Conv3Descriptor(weights=wrong)
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a torch file")
    with pytest.raises(ConfigError, match="cannot read"):
        Conv3Descriptor(weights=garbage)


def test_recognises_gardens_point_across_viewpoint():
    from fdnet.data.groundtruth import GroundTruth
    from fdnet.data.images import load_images
    from fdnet.matching.similarity import top_k

    root = require_shared("gardens_point")
    d = Conv3Descriptor()
    names = [f"Image{i:03d}.jpg" for i in range(40)]
    refs = d.describe(load_images([root / "day_right" / n for n in names], d.input_size))
    queries = d.describe(load_images([root / "day_left" / n for n in names], d.input_size))
    idx, _ = top_k(queries, refs, 1)
    recall = GroundTruth.aligned(40, 40, 2).correct_mask(idx)[:, 0].mean()
    assert recall > 3 * 5 / 40  # chance <= 5/40; measured 0.70
