"""Gist (Oliva & Torralba 2001, LMgist settings)."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.descriptors.gist import GistDescriptor, gabor_bank
from fdnet.errors import ConfigError

from conftest import require_shared


def test_shape_dtype_norm_and_determinism(rng):
    d = GistDescriptor()
    assert d.dim == 512 and d.input_size == (128, 128)
    images = rng.random((3, 128, 128, 3), dtype=np.float32)
    v = d.describe(images)
    assert v.shape == (3, 512) and v.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, rtol=1e-5)
    np.testing.assert_array_equal(d.describe(images), v)
    # batching does not change a vector
    np.testing.assert_allclose(GistDescriptor(batch=1).describe(images), v, rtol=1e-5, atol=1e-6)


def test_filter_bank_peaks_at_lmgist_frequencies_and_angles():
    n = 64
    bank = gabor_bank(n, (8, 8, 8, 8))
    assert bank.shape == (32, n, n)
    f = np.fft.fftfreq(n) * n
    fx, fy = np.meshgrid(f, f)
    for index in (0, 3, 9, 31):
        scale, orientation = divmod(index, 8)
        peak = np.unravel_index(np.argmax(bank[index]), bank[index].shape)
        radius = np.hypot(fx[peak], fy[peak]) / n
        assert radius == pytest.approx(0.3 / 1.85**scale, abs=1.5 / n)
        # the filter is centred where angle + pi*j/8 == 0 (mod pi)
        angle = np.angle(fx[peak] + 1j * fy[peak]) + np.pi * orientation / 8
        assert min(abs(np.sin(angle)), 1.0) < 0.25


def test_oriented_texture_responds_in_matching_orientation():
    # vertical stripes (frequency along x) vs horizontal stripes: energy moves between filters
    y, x = np.mgrid[0:128, 0:128]
    vertical = (0.5 + 0.5 * np.sin(2 * np.pi * x / 8)).astype(np.float32)
    horizontal = vertical.T.copy()
    imgs = np.stack([np.repeat(a[..., None], 3, axis=2) for a in (vertical, horizontal)])
    v = GistDescriptor().describe(imgs).reshape(2, 32, 16).sum(axis=2)
    assert np.argmax(v[0]) != np.argmax(v[1])
    assert v[0] @ v[1] / (np.linalg.norm(v[0]) * np.linalg.norm(v[1])) < 0.8


def test_black_frame_is_finite():
    v = GistDescriptor().describe(np.zeros((2, 128, 128, 3), dtype=np.float32))
    assert np.isfinite(v).all()


def test_bad_settings_are_config_errors():
    with pytest.raises(ConfigError):
        GistDescriptor(image_size=130, grid=4)
    with pytest.raises(ConfigError):
        GistDescriptor(orientations=(8, 0))


def test_recognises_gardens_point_across_viewpoint():
    from fdnet.data.groundtruth import GroundTruth
    from fdnet.data.images import load_images
    from fdnet.matching.similarity import top_k

    root = require_shared("gardens_point")
    d = GistDescriptor()
    names = [f"Image{i:03d}.jpg" for i in range(40)]
    refs = d.describe(load_images([root / "day_right" / n for n in names], d.input_size))
    queries = d.describe(load_images([root / "day_left" / n for n in names], d.input_size))
    idx, _ = top_k(queries, refs, 1, similarity=d.similarity)
    recall = GroundTruth.aligned(40, 40, 2).correct_mask(idx)[:, 0].mean()
    assert recall > 3 * 5 / 40  # chance is at most 5/40 with +-2 frames; measured 0.62
