"""Metrics on hand-made cases whose values are worked out by hand in the comments."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.data.groundtruth import GroundTruth
from fdnet.errors import DataError
from fdnet.metrics import (
    RECALL_OVER_QUERIES,
    VPRBENCH,
    Accepted,
    evaluate_retrieval,
    evaluate_similarity,
    pr_curve_over_queries,
    recall_at_n,
    recall_at_precision,
    top_k_of_matrix,
)


def _case_a():
    """4 queries x 5 references, every query has a true match (reference q).

    Best matches: q0 -> 0 (0.9, correct), q1 -> 4 (0.8, wrong), q2 -> 2 (0.7, correct),
    q3 -> 3 (0.6, correct). Second choices: q1's true reference 1 is its 2nd best.
    """
    s = np.full((4, 5), 0.1)
    s[0, 0] = 0.9
    s[1, 4], s[1, 1] = 0.8, 0.5
    s[2, 2] = 0.7
    s[3, 3] = 0.6
    gt = GroundTruth([[0], [1], [2], [3]], 5)
    return s, gt


def test_recall_over_queries_by_hand():
    s, gt = _case_a()
    m = evaluate_similarity(s, gt, RECALL_OVER_QUERIES)
    # thresholds 0.9, 0.8, 0.7, 0.6 -> (R, P) = (.25, 1), (.25, .5), (.5, 2/3), (.75, .75)
    np.testing.assert_allclose(m.curve.recall, [0, 0.25, 0.25, 0.5, 0.75])
    np.testing.assert_allclose(m.curve.precision, [1, 1, 0.5, 2 / 3, 0.75])
    assert m.recall_at_100_precision == pytest.approx(0.25)
    assert m.precision_at_max_recall == pytest.approx(0.75)
    # trapezoids: .25*1 + 0 + .25*(.5+2/3)/2 + .25*(2/3+.75)/2
    assert m.auc_pr == pytest.approx(0.25 + 0.25 * (0.5 + 2 / 3) / 2 + 0.25 * (2 / 3 + 0.75) / 2)
    assert m.recall_at_n == {1: 0.75, 5: 1.0, 10: 1.0, 20: 1.0}
    assert m.top1_accuracy == 0.75
    assert m.protocol == "recall-over-queries" and m.num_queries == 4


def test_vprbench_by_hand():
    s, gt = _case_a()
    m = evaluate_similarity(s, gt, VPRBENCH)
    # labels [1,0,1,1]; recall divides by the 3 correct top-1 matches:
    # thresholds .9, .8, .7, .6 -> (R, P) = (1/3, 1), (1/3, 1/2), (2/3, 2/3), (1, 3/4)
    np.testing.assert_allclose(m.curve.recall, [0, 1 / 3, 1 / 3, 2 / 3, 1])
    np.testing.assert_allclose(m.curve.precision, [1, 1, 0.5, 2 / 3, 0.75])
    assert m.auc_pr == pytest.approx(1 / 3 * 1 + 1 / 3 * (0.5 + 2 / 3) / 2 + 1 / 3 * (2 / 3 + 0.75) / 2)
    assert m.recall_at_100_precision == pytest.approx(1 / 3)
    assert m.precision_at_max_recall == pytest.approx(0.75)
    assert m.top1_accuracy == 0.75
    assert m.to_dict()["protocol"] == "vprbench"


def test_tied_scores_form_one_threshold():
    # q0 0.9 correct; q1 and q2 both 0.5, one correct, one wrong: no point (2/3, 1) may appear
    retrieved = np.array([[0], [1], [0]])
    scores = np.array([[0.9], [0.5], [0.5]])
    gt = GroundTruth([[0], [1], [2]], 3)
    m = evaluate_retrieval(retrieved, scores, gt, RECALL_OVER_QUERIES)
    np.testing.assert_allclose(m.curve.recall, [0, 1 / 3, 2 / 3])
    np.testing.assert_allclose(m.curve.precision, [1, 1, 2 / 3])
    assert m.recall_at_100_precision == pytest.approx(1 / 3)
    assert m.precision_at_max_recall == pytest.approx(2 / 3)


def test_top_k_ties_keep_lower_index_first():
    s = np.array([[0.5, 0.9, 0.5, 0.5, 0.1], [0.2, 0.2, 0.2, 0.2, 0.2]])
    idx, sc = top_k_of_matrix(s, 2)
    np.testing.assert_array_equal(idx, [[1, 0], [0, 1]])
    np.testing.assert_allclose(sc, [[0.9, 0.5], [0.2, 0.2]])
    idx, _ = top_k_of_matrix(s, 1)
    np.testing.assert_array_equal(idx[:, 0], np.argmax(s, axis=1))  # VPR-Bench's np.argmax


def test_queries_without_true_match():
    s, _ = _case_a()
    # q1 has no true match now: its wrong best match (0.8) is a false positive in both protocols
    gt = GroundTruth([[0], [], [2], [3]], 5)
    m = evaluate_similarity(s, gt, RECALL_OVER_QUERIES)
    assert m.num_queries_with_match == 3
    # recall over the 3 queries with a match: (1/3, 1), (1/3, .5), (2/3, 2/3), (1, .75)
    np.testing.assert_allclose(m.curve.recall, [0, 1 / 3, 1 / 3, 2 / 3, 1])
    assert m.recall_at_n[1] == 1.0  # every query that can be found is found at rank 1
    assert m.precision_at_max_recall == pytest.approx(0.75)
    assert any("no true match" in n for n in m.notes)
    v = evaluate_similarity(s, gt, VPRBENCH)
    assert v.recall_at_n[1] == 0.75  # VPR-Bench divides by all queries
    assert v.top1_accuracy == 0.75


def test_all_correct():
    s = np.eye(6) + 0.01 * np.arange(6)[:, None]
    gt = GroundTruth.aligned(6, 6, 0)
    for protocol in (RECALL_OVER_QUERIES, VPRBENCH):
        m = evaluate_similarity(s, gt, protocol)
        assert m.recall_at_100_precision == 1.0
        assert m.precision_at_max_recall == 1.0
        assert m.auc_pr == pytest.approx(1.0)
        assert m.recall_at_n[1] == 1.0 and m.top1_accuracy == 1.0


def test_none_correct():
    s = np.roll(np.eye(5), 2, axis=1) + 0.01 * np.arange(5)[:, None]  # every best match is 2 off
    gt = GroundTruth.aligned(5, 5, 0)
    for protocol in (RECALL_OVER_QUERIES, VPRBENCH):
        m = evaluate_similarity(s, gt, protocol)
        assert m.recall_at_100_precision == 0.0
        assert m.precision_at_max_recall == 0.0
        assert m.auc_pr == 0.0
        assert m.recall_at_n[1] == 0.0 and m.recall_at_n[5] == 1.0


def test_no_query_has_a_match_is_a_clear_error():
    with pytest.raises(DataError, match="no query has a true match"):
        evaluate_similarity(np.eye(3), GroundTruth([[], [], []], 3))


def test_uniform_thresholds_option():
    s, gt = _case_a()
    # 2 thresholds = the max and min best-match scores: points (.25, 1) and (.75, .75)
    m = evaluate_similarity(s, gt, RECALL_OVER_QUERIES, thresholds=2)
    np.testing.assert_allclose(m.curve.recall, [0, 0.25, 0.75])
    assert m.auc_pr == pytest.approx(0.25 + 0.5 * (1 + 0.75) / 2)
    assert m.thresholds == "2 uniform"
    # 500 thresholds visit every distinct score here, so they match the exact curve's numbers
    exact = evaluate_similarity(s, gt)
    m500 = evaluate_similarity(s, gt, thresholds=500)
    assert len(m500.curve.recall) == 501
    assert m500.auc_pr == pytest.approx(exact.auc_pr)
    assert m500.recall_at_100_precision == exact.recall_at_100_precision
    # min-max normalisation: an affine change of the scores changes nothing
    m_affine = evaluate_similarity(3 * s - 7, gt, thresholds=500)
    np.testing.assert_allclose(m_affine.curve.precision, m500.curve.precision)
    with pytest.raises(DataError, match="recall-over-queries"):
        evaluate_similarity(s, gt, VPRBENCH, thresholds=500)


def test_exact_curve_matches_a_brute_force_sweep(rng):
    # brute force: for every distinct score t count TP/FP among queries with score >= t
    scores = rng.random(50).round(2)  # rounding creates ties
    correct = rng.random(50) < 0.4
    has_match = correct | (rng.random(50) < 0.7)
    curve, _ = pr_curve_over_queries(scores, correct, has_match)
    for t, p, r in zip(curve.thresholds[1:], curve.precision[1:], curve.recall[1:]):
        accepted = scores >= t
        tp = np.count_nonzero(accepted & correct)
        assert p == pytest.approx(tp / accepted.sum())
        assert r == pytest.approx(tp / has_match.sum())


def test_recall_at_n_by_hand():
    correct = np.array([[False, True, False], [False, False, False], [True, False, False]])
    assert recall_at_n(correct, (1, 2, 3)) == {1: 1 / 3, 2: 2 / 3, 3: 2 / 3}
    assert recall_at_n(correct, (1, 2), over=np.array([True, False, True])) == {1: 0.5, 2: 1.0}
    # N beyond the number of candidates uses all of them
    assert recall_at_n(correct, (20,)) == {20: 2 / 3}


def test_shape_mismatch_is_a_clear_error():
    s, gt = _case_a()
    with pytest.raises(DataError, match="4 queries x 5 references"):
        evaluate_similarity(s[:, :4], gt)
    with pytest.raises(DataError, match="unknown protocol"):
        evaluate_similarity(s, gt, "bogus")


def test_top_k_of_matrix_equals_a_stable_full_sort(rng):
    # integer scores: ties everywhere, including at the k-th position
    s = rng.integers(0, 4, (50, 40))
    idx, scores = top_k_of_matrix(s, 7)
    expected = np.argsort(-s, axis=1, kind="stable")[:, :7]
    np.testing.assert_array_equal(idx, expected)
    np.testing.assert_array_equal(scores, np.take_along_axis(s, expected, axis=1))


def test_recall_at_99_and_95_precision_by_hand():
    # 100 queries, scores 100..1; the 60th and 90th most confident are wrong: precision after
    # 59 right = 1, at the 60th 59/60 = 0.983, after 89: 88/89 = 0.989, then 88/90 = 0.978 ...
    scores = np.arange(100, 0, -1, dtype=float)
    correct = np.ones(100, bool)
    correct[[59, 89]] = False
    curve, _ = pr_curve_over_queries(scores, correct, np.ones(100, bool))
    assert recall_at_precision(curve, 1.0) == pytest.approx(0.59)
    # precision >= 0.99 is lost at the 60th query (59/60) and never regained (max 88/89 < 0.99)
    assert recall_at_precision(curve, 0.99) == pytest.approx(0.59)
    # >= 0.95: every point qualifies (lowest 98/100 = 0.98): recall 0.98
    assert recall_at_precision(curve, 0.95) == pytest.approx(0.98)


def test_acceptance_scores_replace_the_best_match_score_but_not_the_ranking():
    s, gt = _case_a()
    idx, top = top_k_of_matrix(s, 5)
    # a rule that trusts q1's match least and vouches for q1's 2nd candidate (its true reference 1)
    score = np.array([0.9, 0.1, 0.7, 0.6])
    match = np.array([0, 1, 2, 3])
    m = evaluate_retrieval(idx, top, gt, RECALL_OVER_QUERIES, accepted=Accepted(score, match, "test"))
    assert m.acceptance == "test" and m.to_dict()["acceptance"] == "test"
    assert m.recall_at_100_precision == 1.0 and m.recall_at_99_precision == 1.0 and m.auc_pr == pytest.approx(1.0)
    assert m.recall_at_n[1] == 0.75 and m.top1_accuracy == 0.75  # ranking unchanged
    # rejected queries (-inf) are never accepted: recall stops at 3/4
    score[1] = -np.inf
    m = evaluate_retrieval(idx, top, gt, RECALL_OVER_QUERIES, accepted=Accepted(score, match))
    assert m.recall_at_100_precision == pytest.approx(0.75) and m.curve.recall.max() == pytest.approx(0.75)
    # VPR-Bench puts every query on the curve: the rejected one sorts last
    m = evaluate_retrieval(idx, top, gt, VPRBENCH, accepted=Accepted(score, match))
    assert m.recall_at_100_precision == pytest.approx(1.0)


def test_acceptance_scores_must_be_one_per_query_and_not_nan():
    s, gt = _case_a()
    idx, top = top_k_of_matrix(s, 5)
    with pytest.raises(DataError, match="one value per query"):
        evaluate_retrieval(idx, top, gt, accepted=Accepted(np.zeros(3), np.zeros(3, int)))
    with pytest.raises(DataError, match="NaN"):
        evaluate_retrieval(idx, top, gt, accepted=Accepted(np.array([1, np.nan, 0, 0]), np.zeros(4, int)))
    with pytest.raises(DataError, match="go together"):
        evaluate_retrieval(idx, top, gt, accepted=Accepted(np.zeros(4), None))
