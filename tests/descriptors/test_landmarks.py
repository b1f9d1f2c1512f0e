"""ConvNet landmarks (Sünderhauf et al. RSS 2015): proposals, packing, mutual-NN matching."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.descriptors.landmarks import LandmarksDescriptor
from fdnet.errors import ConfigError, NotAvailableError

from conftest import require_shared


@pytest.fixture(scope="module")
def small():
    return LandmarksDescriptor(max_regions=6, region_dim=8, input_size=(96, 128), bf16=False)


def _scene(rng, shift=0):
    img = np.full((96, 128, 3), 0.2, np.float32)
    for k, (y, x, h, w) in enumerate([(10, 10, 30, 40), (50, 70, 35, 45), (15, 80, 25, 30)]):
        img[y : y + h, x + shift : x + shift + w] = 0.3 + 0.2 * k
    return np.clip(img + 0.02 * rng.standard_normal(img.shape).astype(np.float32), 0, 1)


def test_pack_unpack_roundtrip_and_layout(small, rng):
    regions = rng.standard_normal((2, 6, 8)).astype(np.float32)
    boxes = rng.random((2, 6, 4)).astype(np.float32)
    valid = rng.random((2, 6)) > 0.5
    packed = small.pack(regions, boxes, valid)
    assert packed.shape == (2, small.dim) and small.dim == 6 * (8 + 5)
    r, b, v = small.unpack(packed)
    np.testing.assert_array_equal(r, regions)
    np.testing.assert_array_equal(b, boxes)
    np.testing.assert_array_equal(v, valid)


def test_describe_shape_determinism_and_self_similarity(small, rng):
    images = np.stack([_scene(rng), _scene(rng, shift=5), rng.random((96, 128, 3), dtype=np.float32)])
    v = small.describe(images)
    assert v.shape == (3, small.dim) and v.dtype == np.float32
    np.testing.assert_array_equal(small.describe(images), v)
    regions, boxes, valid = small.unpack(v)
    assert valid.any(axis=1).all()
    np.testing.assert_allclose(np.linalg.norm(regions[valid], axis=1), 1.0, rtol=1e-4)
    assert (regions[~valid] == 0).all()
    s = small.similarity(v, v)
    assert s.shape == (3, 3)
    # an image matched with itself: every landmark is its own mutual NN at distance 0 and the same
    # shape, so the score is n / sqrt(n * n) = 1
    np.testing.assert_allclose(np.diag(s), 1.0, atol=1e-4)
    assert not small.dot_product_similarity


def test_score_formula_by_hand(small):
    """Two landmarks each; hand-computed mutual matches, cosine distances and shape penalty."""

    def unit(*xs):
        x = np.zeros(8, np.float32)
        x[: len(xs)] = xs
        return x / np.linalg.norm(x)

    q_regions = np.zeros((1, 6, 8), np.float32)
    r_regions = np.zeros((1, 6, 8), np.float32)
    q_regions[0, 0], q_regions[0, 1] = unit(1, 0), unit(0, 1)
    r_regions[0, 0], r_regions[0, 1], r_regions[0, 2] = unit(1, 0.2), unit(0.1, 1), unit(-1, 0)
    q_boxes = np.zeros((1, 6, 4), np.float32)
    r_boxes = np.zeros((1, 6, 4), np.float32)
    q_boxes[0, :2] = [(0, 0, 0.2, 0.4), (0.5, 0.5, 0.3, 0.3)]
    r_boxes[0, :3] = [(0, 0, 0.2, 0.2), (0.5, 0.5, 0.3, 0.3), (0, 0, 0.1, 0.1)]
    q_valid = np.zeros((1, 6), bool)
    r_valid = np.zeros((1, 6), bool)
    q_valid[0, :2] = True
    r_valid[0, :3] = True
    q = small.pack(q_regions, q_boxes, q_valid)
    r = small.pack(r_regions, r_boxes, r_valid)
    d0 = 1 - q_regions[0, 0] @ r_regions[0, 0]
    d1 = 1 - q_regions[0, 1] @ r_regions[0, 1]
    s0 = np.exp(0.5 * (0 / 0.2 + 0.2 / 0.4))  # widths equal, heights 0.4 vs 0.2
    s1 = 1.0
    expected = ((1 - d0 * s0) + (1 - d1 * s1)) / np.sqrt(2 * 3)
    assert small.similarity(q, r)[0, 0] == pytest.approx(expected, abs=1e-5)


def test_black_frame_has_no_landmarks_and_scores_zero(small, rng):
    v = small.describe(np.stack([np.zeros((96, 128, 3), np.float32), _scene(rng)]))
    _, _, valid = small.unpack(v)
    assert not valid[0].any()
    s = small.similarity(v, v)
    assert np.isfinite(s).all() and (s[0] == 0).all() and (s[:, 0] == 0).all()


def test_missing_or_bad_edge_model_is_a_clear_error(tmp_path):
    with pytest.raises(NotAvailableError, match="model.yml.gz"):
        LandmarksDescriptor(edge_model=tmp_path / "model.yml.gz")
    bad = tmp_path / "bad.yml.gz"
    bad.write_bytes(b"not a model")
    with pytest.raises(ConfigError, match="not a structured-edge model"):
        LandmarksDescriptor(edge_model=bad)
    with pytest.raises(ConfigError):
        LandmarksDescriptor(max_regions=0)


def test_recognises_gardens_point_across_viewpoint():
    from fdnet.data.groundtruth import GroundTruth
    from fdnet.data.images import load_images
    from fdnet.matching.similarity import top_k

    root = require_shared("gardens_point")
    d = LandmarksDescriptor()
    names = [f"Image{i:03d}.jpg" for i in range(40)]
    refs = d.describe(load_images([root / "day_right" / n for n in names], d.input_size))
    queries = d.describe(load_images([root / "day_left" / n for n in names], d.input_size))
    idx, _ = top_k(queries, refs, 1, similarity=d.similarity)
    recall = GroundTruth.aligned(40, 40, 2).correct_mask(idx)[:, 0].mean()
    assert recall > 3 * 5 / 40  # chance <= 5/40; measured 0.78
