"""`trunk`: the frozen map FDNet reads, alone; with an FDNet run, that run's block and size."""

import numpy as np
import pytest

from fdnet import runs
from fdnet.config import replace_dotted
from fdnet.descriptors import create
from fdnet.errors import ConfigError
from fdnet.methods.fdnet.config import preset
from fdnet.methods.fdnet.model import FDNet


def _run(tmp_path, **model):
    config = replace_dotted(preset("tiny"), {f"model.{k}": v for k, v in model.items()})
    runs.save_weights(tmp_path / "run", FDNet(config.model).named_parts(), config)
    return tmp_path / "run"


def test_default_is_the_cpu_presets_map_unprojected():
    trunk = create("trunk", bf16=False)
    assert trunk.input_size == (128, 256) and trunk.dim == 80 * 8 * 16
    images = np.random.default_rng(0).random((2, 128, 256, 3), dtype=np.float32)
    vectors = trunk.describe(images)
    assert vectors.shape == (2, trunk.dim)
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-5)
    # the same map conv3 computes, without the random projection
    conv3 = create("conv3", dim=0, input_size=[128, 256], bf16=False)
    np.testing.assert_allclose(vectors, conv3.describe(images), atol=1e-5)


def test_with_an_fdnet_run_it_reads_what_the_run_reads(tmp_path):
    run = _run(tmp_path, backbone="efficientnet-lite0", backbone_block=4, input_size=[32, 64], widths=[16])
    trunk = create("trunk", checkpoint=str(run))
    assert trunk.input_size == (32, 64) and trunk.dim == 40 * 4 * 8
    assert trunk.settings()["checkpoint"] == str(run)


def test_a_pixel_run_has_no_trunk(tmp_path):
    with pytest.raises(ConfigError, match="no trunk"):
        create("trunk", checkpoint=str(_run(tmp_path)))


# ----------------------------------------------------------------------------------- backbones
def test_any_shipped_backbone_and_block():
    trunk = create("trunk", backbone="efficientnet-lite2", block=12, bf16=False)
    assert trunk.dim == 120 * 8 * 16  # 15,360 at 128x256
    assert trunk.settings()["backbone"] == "efficientnet-lite2 (ImageNet)" and trunk.settings()["block"] == 12
    assert create("trunk", backbone="efficientnet-lite1", block=20, input_size=[64, 64], bf16=False).dim == 320 * 2 * 2
    with pytest.raises(ConfigError, match=r"efficientnet-lite2 has blocks 0..20"):
        create("trunk", backbone="efficientnet-lite2", block=21)
    with pytest.raises(ConfigError, match="not a shipped backbone"):
        create("trunk", backbone="efficientnet-b0")


# ------------------------------------------------------------------------------ trunk-whitened
SMALL = dict(block=4, input_size=[32, 64], bf16=False)  # 40 x 4 x 8 = 1280 values


def _made_images(n, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.random((4, 32, 64, 3), dtype=np.float32)
    mix = rng.random((n, 4)).astype(np.float32)
    return np.clip(
        np.einsum("nk,khwc->nhwc", mix / mix.sum(1, keepdims=True), base)
        + 0.05 * rng.random((n, 32, 64, 3), dtype=np.float32),
        0,
        1,
    )


def test_whitening_learnt_from_made_images_equals_an_independent_pca():
    from sklearn.decomposition import PCA

    train, test = _made_images(16), _made_images(5, seed=1)
    whitened = create("trunk-whitened", dim=6, power=1.0, **SMALL)  # full whitening, as sklearn's
    assert whitened.needs_fit and whitened.dim == 6
    unfitted = whitened.fingerprint()  # reproduce keys its caches on the unfitted copy
    whitened.fit(train)
    assert whitened.fingerprint() != unfitted
    assert not whitened.needs_fit and whitened.settings()["fitted_on"] == "reference images (16)"
    got = whitened.describe(test)
    # independently: the trunk's own vectors, scikit-learn's whitening PCA, L2
    trunk = create("trunk", **SMALL)
    pca = PCA(n_components=6, whiten=True, svd_solver="full").fit(trunk.describe(train))
    expected = pca.transform(trunk.describe(test))
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    assert got.shape == (5, 6)
    np.testing.assert_allclose(got @ got.T, expected @ expected.T, atol=2e-3)


def _dataset(root, n=8):
    from PIL import Image

    for k, condition in enumerate(("summer", "winter")):
        (root / condition).mkdir(parents=True)
        for i, image in enumerate(_made_images(n, seed=10 + k)):
            Image.fromarray((image * 255).astype(np.uint8)).save(root / condition / f"{i:03d}.png")
    return root


def test_fit_folder_and_its_frames(tmp_path):
    data = _dataset(tmp_path / "data")
    whitened = create("trunk-whitened", dim=5, fit=str(data), fit_frames="0:4", **SMALL)
    assert not whitened.needs_fit  # it learns from the folder, not from the references
    fitted_on = whitened.settings()["fitted_on"]
    assert "frames 0:4: 8 images of summer (4), winter (4)" in fitted_on
    vectors = whitened.describe(_made_images(3))
    assert vectors.shape == (3, 5)
    # the same folder gives the same whitening, so a database can rebuild it
    again = create("trunk-whitened", dim=5, fit=str(data), fit_frames="0:4", **SMALL)
    assert again.fingerprint() == whitened.fingerprint()
    assert create("trunk-whitened", dim=5, fit=str(data), **SMALL).fingerprint() != whitened.fingerprint()


def test_bad_settings(tmp_path):
    with pytest.raises(ConfigError, match=r"dim 2000 is larger than the map it whitens allows \(40 x 4 x 8 = 1280"):
        create("trunk-whitened", dim=2000, **SMALL)
    data = _dataset(tmp_path / "data", n=4)
    with pytest.raises(ConfigError, match=r"more than 8 fitting images allow \(at most 7"):
        create("trunk-whitened", dim=8, fit=str(data), **SMALL)
    with pytest.raises(ConfigError, match="fit_frames .* needs fit=DIR"):
        create("trunk-whitened", dim=4, fit_frames="0:2", **SMALL)
    with pytest.raises(ConfigError, match="whole number"):
        create("trunk-whitened", dim=0, **SMALL)
    with pytest.raises(ConfigError, match=r"trunk-whitened: power=-0.5: must be a number >= 0"):
        create("trunk-whitened", power=-0.5, **SMALL)
    whitened = create("trunk-whitened", dim=10, **SMALL)
    with pytest.raises(ConfigError, match="no whitening yet"):
        whitened.describe(_made_images(2))
    with pytest.raises(ConfigError, match="L = 10 dimensions, but 6 fitting vectors"):
        whitened.fit(_made_images(6))
