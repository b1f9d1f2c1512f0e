"""DBoW: ORB vocabulary tree, TF-IDF, L1 score (Gálvez-López & Tardós 2012)."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.descriptors.dbow import DBoWDescriptor, Vocabulary
from fdnet.errors import ConfigError, NotAvailableError

from conftest import require_shared


def _clustered_descriptors(rng, prototypes=4, per=60, flip=0.05):
    protos = rng.integers(0, 2, size=(prototypes, 256)).astype(np.uint8)
    noise = (rng.random((prototypes, per, 256)) < flip).astype(np.uint8)
    bits = protos[:, None, :] ^ noise
    return protos, np.packbits(bits.reshape(-1, 256), axis=1), np.repeat(np.arange(prototypes), per)


def test_vocabulary_recovers_binary_clusters(rng):
    protos, packed, cluster = _clustered_descriptors(rng)
    # 8 "images", each holding a slice of every cluster
    images = [packed[i::8] for i in range(8)]
    vocab = Vocabulary.learn(images, branching=4, depth=1, seed=0)
    assert vocab.num_words == 4
    words = vocab.words(packed)
    # every cluster maps to one word, and different clusters to different words
    mapping = {c: set(words[cluster == c]) for c in range(4)}
    assert all(len(w) == 1 for w in mapping.values())
    assert len(set.union(*mapping.values())) == 4
    # each prototype's centre is the majority bit pattern: the prototype itself
    assert set(vocab.words(np.packbits(protos, axis=1))) == set(words)


def test_tfidf_bow_and_l1_score(rng):
    _, packed, cluster = _clustered_descriptors(rng)
    # image i sees clusters i and i+1 (mod 4): every word is in some images but not all, so its
    # IDF is positive (a word in every training image gets weight log(1) = 0, as in DBoW2)
    images = [packed[np.isin(cluster, [i % 4, (i + 1) % 4])][i::8] for i in range(8)]
    vocab = Vocabulary.learn(images, branching=2, depth=3, seed=1)
    assert (vocab.idf > 0).any()
    d = DBoWDescriptor()
    d.vocabulary = vocab
    v = np.stack([vocab.bow(f) for f in images[:3]] + [vocab.bow(np.zeros((0, 32), np.uint8))])
    np.testing.assert_allclose(v[:3].sum(1), 1.0, rtol=1e-5)
    assert (v[3] == 0).all()
    s = d.similarity(v, v)
    for i in range(3):
        for j in range(3):
            expected = 1 - 0.5 * np.abs(v[i] - v[j]).sum()
            assert s[i, j] == pytest.approx(expected, abs=1e-5)
    assert (s[3] == 0).all() and (s[:, 3] == 0).all()
    assert s[0, 0] == pytest.approx(1.0)
    assert not d.dot_product_similarity


def test_black_frames_do_not_crash_and_score_zero(rng):
    d = DBoWDescriptor(input_size=(96, 128), depth=2)
    textured = rng.random((4, 96, 128, 3), dtype=np.float32)
    d.fit(textured)
    v = d.describe(np.concatenate([np.zeros((1, 96, 128, 3), np.float32), textured[:1]]))
    assert v.shape == (2, d.dim) and v.dtype == np.float32
    assert (v[0] == 0).all()
    assert (d.similarity(v, v)[0] == 0).all()


def test_needs_fit_describe_errors_and_fit_warns(rng, caplog):
    d = DBoWDescriptor(input_size=(96, 128), depth=2)
    assert d.needs_fit
    with pytest.raises(ConfigError, match="no vocabulary"):
        d.describe(rng.random((1, 96, 128, 3), dtype=np.float32))
    with caplog.at_level("WARNING"):
        d.fit(rng.random((3, 96, 128, 3), dtype=np.float32))
    assert "learned one" in caplog.text
    assert not d.needs_fit


def test_vocabulary_file_roundtrip_and_bad_files(tmp_path, rng):
    images = rng.random((4, 96, 128, 3), dtype=np.float32)
    d = DBoWDescriptor(input_size=(96, 128), depth=2)
    d.fit(images)
    path = tmp_path / "voc.safetensors"
    d.vocabulary.save(path)
    loaded = DBoWDescriptor(vocabulary=path, input_size=(96, 128))
    assert not loaded.needs_fit and loaded.dim == d.dim
    np.testing.assert_array_equal(loaded.describe(images), d.describe(images))
    with pytest.raises(NotAvailableError, match="not found"):
        DBoWDescriptor(vocabulary=tmp_path / "missing.safetensors")
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"\x00" * 40)
    with pytest.raises(ConfigError, match="not a DBoW vocabulary"):
        DBoWDescriptor(vocabulary=bad)


def test_recognises_gardens_point_across_viewpoint():
    from fdnet.data.groundtruth import GroundTruth
    from fdnet.data.images import load_images
    from fdnet.matching.similarity import top_k

    root = require_shared("gardens_point")
    d = DBoWDescriptor(depth=3)
    names = [f"Image{i:03d}.jpg" for i in range(40)]
    refs = load_images([root / "day_right" / n for n in names], d.input_size)
    d.fit(refs)
    r = d.describe(refs)
    q = d.describe(load_images([root / "day_left" / n for n in names], d.input_size))
    idx, _ = top_k(q, r, 1, similarity=d.similarity)
    recall = GroundTruth.aligned(40, 40, 2).correct_mask(idx)[:, 0].mean()
    assert recall > 3 * 5 / 40  # chance <= 5/40; measured 0.62 (depth 3), 0.70 (depth 4)


def test_fit_folder_learns_the_vocabulary_and_says_so(tmp_path, rng):
    from PIL import Image

    for condition in ("day", "night"):
        (tmp_path / "data" / condition).mkdir(parents=True)
        for i in range(4):
            Image.fromarray((rng.random((96, 128, 3)) * 255).astype(np.uint8)).save(
                tmp_path / "data" / condition / f"{i}.png"
            )
    d = DBoWDescriptor(input_size=(96, 128), depth=2, fit=str(tmp_path / "data"), fit_frames="0:3")
    assert not d.needs_fit and d.vocabulary.info["training_images"] == 6
    settings = d.settings()
    assert "frames 0:3: 6 images of day (3), night (3)" in settings["fitted_on"]
    assert settings["vocabulary"].startswith("learned from ") and settings["fit_frames"] == "0:3"
    reference_fitted = DBoWDescriptor(input_size=(96, 128), depth=2)
    assert reference_fitted.settings()["fitted_on"] is None
    reference_fitted.fit(rng.random((3, 96, 128, 3), dtype=np.float32))
    assert reference_fitted.settings()["fitted_on"] == "reference images (3)"
    with pytest.raises(ConfigError, match="not both"):
        DBoWDescriptor(vocabulary=tmp_path / "v.safetensors", fit=str(tmp_path / "data"))
    with pytest.raises(ConfigError, match="needs fit=DIR"):
        DBoWDescriptor(fit_frames="0:3")
