import numpy as np
import pytest

from fdnet.matching.similarity import similarity_matrix, top_k


def test_similarity_matrix_blocks_equal_full_product(rng):
    q = rng.normal(size=(37, 8)).astype(np.float32)
    r = rng.normal(size=(53, 8)).astype(np.float32)
    np.testing.assert_allclose(similarity_matrix(q, r, block=7), q @ r.T, rtol=1e-5, atol=1e-5)


def test_top_k_matches_full_sort_across_blocks(rng):
    q = rng.normal(size=(50, 8)).astype(np.float32)
    r = rng.normal(size=(300, 8)).astype(np.float32)
    idx, scores = top_k(q, r, 5, block_queries=7, block_references=33)
    full = q @ r.T
    expected = np.argsort(-full, axis=1, kind="stable")[:, :5]
    np.testing.assert_array_equal(idx, expected)
    np.testing.assert_allclose(scores, np.take_along_axis(full, expected, 1), rtol=1e-6)


def test_top_k_ties_prefer_lower_index():
    q = np.ones((1, 2), np.float32)
    r = np.ones((6, 2), np.float32)
    idx, _ = top_k(q, r, 3, block_references=4)
    assert idx.tolist() == [[0, 1, 2]]


def test_top_k_custom_similarity_and_k_larger_than_map(rng):
    q = rng.normal(size=(4, 3)).astype(np.float32)
    r = rng.normal(size=(3, 3)).astype(np.float32)

    def neg_l1(a, b):
        return -np.abs(a[:, None, :] - b[None, :, :]).sum(-1)

    idx, scores = top_k(q, r, 10, similarity=neg_l1)
    assert idx.shape == (4, 3)
    np.testing.assert_array_equal(idx[:, 0], neg_l1(q, r).argmax(1))


def test_top_k_rejects_empty_map():
    with pytest.raises(ValueError):
        top_k(np.zeros((1, 2), np.float32), np.zeros((0, 2), np.float32), 1)


def test_top_k_of_matrix_equals_streaming_top_k(rng):
    from fdnet.matching.similarity import top_k_of_matrix

    q = rng.normal(size=(20, 4)).astype(np.float32)
    r = rng.normal(size=(30, 4)).astype(np.float32)
    a_idx, a_s = top_k_of_matrix(q @ r.T, 4)
    b_idx, b_s = top_k(q, r, 4)
    np.testing.assert_array_equal(a_idx, b_idx)
    np.testing.assert_allclose(a_s, b_s, rtol=1e-6)
    full_idx, _ = top_k_of_matrix(q @ r.T, 30)
    np.testing.assert_array_equal(full_idx, np.argsort(-(q @ r.T), axis=1, kind="stable"))
