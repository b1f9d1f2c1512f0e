import numpy as np
import pytest

from fdnet.errors import ConfigError
from fdnet.matching.index import IndexSettings, VectorIndex
from fdnet.matching.similarity import top_k


def unit(rng, n, d):
    v = rng.normal(size=(n, d)).astype(np.float32)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_flat_index_equals_exact_top_k(rng):
    refs, queries = unit(rng, 400, 16), unit(rng, 30, 16)
    index = VectorIndex(16)
    index.add(refs[:150])
    index.add(refs[150:])
    idx, scores = index.search(queries, 5)
    exact_idx, exact_scores = top_k(queries, refs, 5)
    np.testing.assert_array_equal(idx, exact_idx)
    np.testing.assert_allclose(scores, exact_scores, rtol=1e-5)


@pytest.mark.parametrize("kind", ["hnsw", "ivf"])
def test_approximate_indexes_find_exact_duplicates(rng, kind):
    refs = unit(rng, 3000, 16)
    index = VectorIndex(16, IndexSettings(kind=kind))
    index.add(refs)
    idx, _ = index.search(refs[:100], 1)
    assert (idx[:, 0] == np.arange(100)).mean() > 0.95
    assert len(index) == 3000
    np.testing.assert_allclose(index.reconstruct_all()[:5], refs[:5], rtol=1e-6)


def test_index_rejects_wrong_dimension_and_kind(rng):
    index = VectorIndex(8)
    with pytest.raises(ConfigError, match="8-d"):
        index.add(unit(rng, 3, 4))
    with pytest.raises(ConfigError, match="empty"):
        index.search(unit(rng, 1, 8), 1)
    with pytest.raises(ConfigError, match="unknown index kind"):
        VectorIndex(8, IndexSettings(kind="lsh"))


@pytest.mark.parametrize("kind", ["flat", "ivf"])
def test_search_below_an_index_keeps_the_earlier_vectors_only(kind):
    rng = np.random.default_rng(7)
    x = rng.standard_normal((5000, 16)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    index = VectorIndex(16, IndexSettings(kind=kind, ivf_probe=64))
    index.add(x)
    ids, scores = index.search(x[4000:4010], 3, below=4000)
    assert (ids >= 0).all() and (ids < 4000).all()
    np.testing.assert_array_equal(ids, np.argsort(-(x[4000:4010] @ x[:4000].T), axis=1)[:, :3])
    assert (index.search(x[4000:4010], 1)[0][:, 0] == np.arange(4000, 4010)).all()  # without: themselves
    hnsw = VectorIndex(16, IndexSettings(kind="hnsw"))
    hnsw.add(x[:100])
    with pytest.raises(ConfigError, match="cannot search a prefix"):
        hnsw.search(x[:1], 1, below=50)
