"""PCA whitening (Jegou & Chum 2012) against independent computations: scikit-learn's PCA with
whiten=True and numpy's covariance eigendecomposition."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.decomposition import PCA

from fdnet.descriptors.whitening import PCAWhitening, max_whitening_dim
from fdnet.errors import ConfigError, DataError


def _l2(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _correlated(rng, n, d):
    # a few strong directions plus noise: unequal eigenvalues, so whitening changes the cosines
    basis = rng.standard_normal((6, d))
    return rng.standard_normal((n, 6)) * np.array([9, 5, 3, 2, 1, 0.5]) @ basis + 0.3 * rng.standard_normal((n, d))


@pytest.mark.parametrize("n, d, dim", [(40, 300, 12), (300, 20, 12)])  # Gram and covariance branches
def test_equals_sklearn_pca_whiten(rng, n, d, dim):
    train = _correlated(rng, n, d)
    test = _correlated(rng, 15, d)
    ours = PCAWhitening.fit(train, dim)
    sk = PCA(n_components=dim, whiten=True, svd_solver="full").fit(_l2(train))
    expected = _l2(sk.transform(_l2(test)))
    got = ours.transform(test)
    np.testing.assert_allclose(ours.eigenvalues, sk.explained_variance_, rtol=1e-4)
    # each direction's sign is arbitrary in both, so compare what matching uses: the cosines
    np.testing.assert_allclose(got @ got.T, expected @ expected.T, atol=1e-4)
    np.testing.assert_allclose(np.abs(np.sum(ours.components * sk.components_, axis=1)), 1.0, atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)


def test_training_vectors_come_out_white(rng):
    train = _correlated(rng, 60, 50)
    w = PCAWhitening.fit(train, 10)
    unnormalised = (_l2(train) - w.mean) @ w._projection  # before the final L2 normalisation
    np.testing.assert_allclose(np.cov(unnormalised, rowvar=False), np.eye(10), atol=1e-4)


def test_power_zero_is_a_plain_pca_projection_and_power_half_between(rng):
    train = _correlated(rng, 50, 80)
    x = _correlated(rng, 5, 80)
    plain = PCAWhitening.fit(train, 8, power=0.0)
    values, vectors = np.linalg.eigh(np.cov(_l2(train), rowvar=False))
    top = vectors[:, np.argsort(values)[::-1][:8]]
    expected = _l2((_l2(x) - _l2(train).mean(0)) @ top)
    got = plain.transform(x)
    np.testing.assert_allclose(got @ got.T, expected @ expected.T, atol=1e-4)
    half = PCAWhitening.fit(train, 8, power=0.5)
    np.testing.assert_allclose(half._projection, half.components.T / half.eigenvalues**0.25, rtol=1e-5)


def test_deterministic_signs(rng):
    train = _correlated(rng, 30, 40)
    a, b = PCAWhitening.fit(train, 5), PCAWhitening.fit(train[::-1].copy(), 5)
    np.testing.assert_allclose(a.components, b.components, atol=1e-5)


def test_limits_and_bad_input(rng):
    assert max_whitening_dim(100, 10240) == 99 and max_whitening_dim(5000, 64) == 64
    train = _correlated(rng, 20, 30)
    with pytest.raises(ConfigError, match=r"L = 20 dimensions, but 20 fitting vectors of length 30 allow 1..19"):
        PCAWhitening.fit(train, 20)
    with pytest.raises(ConfigError, match="allow 1..19"):
        PCAWhitening.fit(train, 0)
    with pytest.raises(ConfigError, match="power must be"):
        PCAWhitening.fit(train, 4, power=-1)
    with pytest.raises(DataError, match="span only 2 directions"):
        PCAWhitening.fit(np.repeat(train[:3], 10, axis=0), 5)
    with pytest.raises(DataError, match="NaN"):
        PCAWhitening.fit(np.full((5, 4), np.nan), 2)
    with pytest.raises(DataError, match="vectors of length 30"):
        PCAWhitening.fit(train, 4).transform(np.ones((2, 31)))


def test_a_shorter_whitening_is_the_leading_part_of_a_longer_one(rng):
    # what lets one decomposition serve every L (docs/trunk.md's measurements rely on it)
    train = _correlated(rng, 40, 60)
    x = _correlated(rng, 6, 60)
    long, short = PCAWhitening.fit(train, 20), PCAWhitening.fit(train, 7)
    cut = PCAWhitening(long.mean, long.components[:7], long.eigenvalues[:7])
    np.testing.assert_allclose(cut.transform(x), short.transform(x), atol=1e-4)
