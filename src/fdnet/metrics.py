"""Place-recognition metrics over top-k retrievals (or a full similarity matrix) and a GroundTruth.

Everything starts from each query's ranked candidates: ``retrieved`` (Q, k) reference indices,
best first, with their ``scores`` (Q, k), higher = more similar. The best match (column 0) and its
score drive the precision-recall (PR) curve; the first N columns drive Recall@N. A full (Q, R)
matrix is only needed to obtain these (:func:`top_k_of_matrix`), so maps too large for a matrix
are evaluated from :func:`fdnet.matching.similarity.top_k` directly.

Two protocols, because the field uses two incompatible definitions of "recall" for the same
curve. Every result names the one it used (``Metrics.protocol``) and its definition.

``vprbench`` -- exactly as VPR-Bench computes it (Zaffar et al., "VPR-Bench: An Open-Source
    Visual Place Recognition Evaluation Framework with Quantifiable Viewpoint and Appearance
    Change", IJCV 2021; code: github.com/MubarizZaffar/VPR-Bench, ``performance_comparison.py``:
    ``compute_matches``, ``compute_precision_recall``, ``compute_auc_PR``, ``compute_accuracy``,
    ``compute_RecallRateAtN``). Each query contributes its top-1 match (``np.argmax``: the lowest
    index among equal scores) labelled correct (1) or incorrect (0); the PR curve is
    ``sklearn.metrics.precision_recall_curve(labels, top1_scores)`` and AUC-PR is
    ``sklearn.metrics.auc(recall, precision)`` (trapezoidal). Recall is therefore
    TP / (number of correct top-1 matches): it always reaches 1 at the lowest threshold, whatever
    the accuracy. Top-1 accuracy = correct top-1 matches / all queries; Recall@N also divides by
    all queries (a query without a true match counts as a miss), as VPR-Bench does.

``recall-over-queries`` -- the definition of the paper (Qin et al., section 5.1.2, eq. 12) and of
    VPR_Tutorial (Schubert et al., "Visual Place Recognition: A Tutorial", IEEE RAM 2023; code:
    github.com/stschubert/VPR_Tutorial ``metrics.py``, ``createPR`` with
    ``matching='single'``). A threshold t accepts every query whose best-match score is >= t;
    TP = accepted queries whose best match is correct, FP = accepted queries whose best match is
    wrong (queries without any true match can only add FPs), precision = TP / (TP + FP),
    recall = TP / (number of queries that have a true match). By default every distinct best-match
    score is a threshold (the exact curve); ``thresholds=N`` instead sweeps N thresholds uniformly
    over the min-max-normalised best-match scores, i.e. ``linspace(max, min, N)`` as createPR does
    (the paper uses N = 500). The curve starts at (recall 0, precision 1) as in createPR; AUC-PR is
    the trapezoidal area under it (VPR_Tutorial's demo uses ``np.trapz(P, R)``). Recall@N divides
    by the queries that have a true match (as VPR_Tutorial's ``recallAtK``).

Summary numbers, the same for both protocols (paper 5.1.2; VPR_Tutorial ``recallAt100precision``):
R@100P = the largest recall on the curve whose precision is exactly 1 (0 if even the most
confident match is wrong); R@99P and R@95P the same at precision >= 0.99 and >= 0.95; P@maxR =
the precision at the largest recall the curve reaches (the best such precision when several
thresholds reach it; the synthetic start point never counts).

**Acceptance scores.** By default the PR curve thresholds each query's best-match similarity (the
``raw`` rule). :func:`evaluate_retrieval` can instead take one acceptance score per query and the
reference it vouches for (:func:`fdnet.decisions.acceptance.decide`: ``margin``, ``ratio``...);
the curve then thresholds those scores and a query counts as correct when *that* reference is.
A score of ``-inf`` (rejected by a gate) is never accepted under ``recall-over-queries``; under
``vprbench``, where every query's top-1 is on the curve, it sorts below every other score.
Recall@N and top-1 accuracy always come from the ranking itself, whatever the rule.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fdnet.data.groundtruth import GroundTruth
from fdnet.errors import DataError
from fdnet.matching.similarity import top_k_of_matrix  # noqa: F401  (re-exported: metrics API)

VPRBENCH = "vprbench"
RECALL_OVER_QUERIES = "recall-over-queries"

#: protocol name -> one-line definition, written next to every result
PROTOCOLS: dict[str, str] = {
    VPRBENCH: (
        "VPR-Bench (Zaffar et al. IJCV 2021): PR over top-1 scores labelled correct/incorrect, "
        "recall = TP / correct top-1 matches, AUC = sklearn auc(recall, precision); "
        "Recall@N and accuracy over all queries"
    ),
    RECALL_OVER_QUERIES: (
        "recall over queries (paper 5.1.2, VPR_Tutorial createPR 'single'): threshold on best-match "
        "score, precision = TP / (TP + FP), recall = TP / queries with a true match; "
        "Recall@N over queries with a true match"
    ),
}

DEFAULT_NS = (1, 5, 10, 20)


@dataclass
class PRCurve:
    """Points of a PR curve ordered by increasing recall (decreasing threshold).

    ``thresholds[i]`` is the score threshold of point i; the synthetic start point
    (recall 0, precision 1), when present, has threshold +inf.
    """

    precision: np.ndarray
    recall: np.ndarray
    thresholds: np.ndarray

    def to_dict(self, decimals: int = 6) -> dict:
        def rounded(a: np.ndarray) -> list:
            return [None if not np.isfinite(v) else round(float(v), decimals) for v in a]

        return {
            "precision": rounded(self.precision),
            "recall": rounded(self.recall),
            "thresholds": rounded(self.thresholds),
        }


@dataclass
class Metrics:
    """All metrics of one method on one split under one protocol."""

    protocol: str
    num_queries: int
    num_queries_with_match: int
    recall_at_100_precision: float
    precision_at_max_recall: float
    auc_pr: float
    recall_at_n: dict[int, float]
    top1_accuracy: float
    curve: PRCurve
    thresholds: str = "exact"
    notes: list[str] = field(default_factory=list)
    recall_at_99_precision: float = 0.0
    recall_at_95_precision: float = 0.0
    #: the acceptance rule whose scores the PR curve thresholds (``raw``: best-match similarity)
    acceptance: str = "raw"

    @property
    def definition(self) -> str:
        return PROTOCOLS[self.protocol]

    def to_dict(self, include_curve: bool = True) -> dict:
        out = {
            "protocol": self.protocol,
            "protocol_definition": self.definition,
            "thresholds": self.thresholds,
            "num_queries": self.num_queries,
            "num_queries_with_match": self.num_queries_with_match,
            "acceptance": self.acceptance,
            "recall_at_100_precision": self.recall_at_100_precision,
            "recall_at_99_precision": self.recall_at_99_precision,
            "recall_at_95_precision": self.recall_at_95_precision,
            "precision_at_max_recall": self.precision_at_max_recall,
            "auc_pr": self.auc_pr,
            "recall_at_n": {str(n): v for n, v in self.recall_at_n.items()},
            "top1_accuracy": self.top1_accuracy,
        }
        if self.notes:
            out["notes"] = list(self.notes)
        if include_curve:
            out["pr_curve"] = self.curve.to_dict()
        return out


# ---------------------------------------------------------------------------- ranking
# ---------------------------------------------------------------------------- PR curves
def pr_curve_vprbench(scores: np.ndarray, correct: np.ndarray) -> tuple[PRCurve, float]:
    """VPR-Bench's PR curve and AUC-PR from top-1 ``scores`` and their ``correct`` labels.

    Calls the same scikit-learn functions VPR-Bench calls (``precision_recall_curve``, ``auc``).
    When no top-1 match is correct, scikit-learn's recall is undefined (0/0); the curve is then
    a single point (recall 0, precision 0) and AUC 0, which is what a method that never finds the
    place deserves.
    """
    from sklearn.metrics import auc, precision_recall_curve

    scores = np.asarray(scores, dtype=np.float64)
    correct = np.asarray(correct, dtype=bool)
    if not correct.any():
        curve = PRCurve(np.array([1.0, 0.0]), np.array([0.0, 0.0]), np.array([np.inf, scores.min()]))
        return curve, 0.0
    precision, recall, thr = precision_recall_curve(correct.astype(int), scores)
    auc_pr = float(auc(recall, precision))
    # scikit-learn orders by increasing threshold (decreasing recall) and appends the
    # (precision 1, recall 0) point without a threshold; flip to increasing recall.
    thresholds = np.concatenate([thr, [np.inf]])
    return PRCurve(precision[::-1].copy(), recall[::-1].copy(), thresholds[::-1].copy()), auc_pr


def pr_curve_over_queries(
    scores: np.ndarray, correct: np.ndarray, has_match: np.ndarray, thresholds: int | None = None
) -> tuple[PRCurve, float]:
    """Recall-over-queries PR curve and its trapezoidal AUC (see the module docstring).

    ``thresholds=None``: every distinct best-match score (exact); ``thresholds=N``: N values
    ``linspace(max, min, N)`` of the best-match scores (the paper's 500 uniform values of the
    min-max-normalised similarity).
    """
    scores = np.asarray(scores, dtype=np.float64)
    correct = np.asarray(correct, dtype=bool)
    num_positive = int(np.count_nonzero(has_match))
    if num_positive == 0:
        raise DataError("no query has a true match in the ground truth, so recall is undefined")
    order = np.argsort(-scores, kind="stable")
    desc = scores[order]
    cum_tp = np.concatenate([[0], np.cumsum(correct[order])])
    # -inf = rejected by an acceptance gate: never a threshold, so never accepted
    finite = desc[np.isfinite(desc)]
    if thresholds is None:
        thr = np.unique(finite)[::-1]
    else:
        if thresholds < 2:
            raise DataError(f"--thresholds must be at least 2, got {thresholds}")
        thr = np.linspace(finite[0], finite[-1], int(thresholds)) if len(finite) else finite
    # number of queries accepted at each threshold (score >= t); -desc is ascending
    accepted = np.searchsorted(-desc, -thr, side="right")
    tp = cum_tp[accepted]
    # precision = TP / (TP + FP) = TP / accepted; nothing accepted = no false positive yet (1)
    precision = np.where(accepted > 0, tp / np.maximum(accepted, 1), 1.0)
    recall = tp / num_positive
    precision = np.concatenate([[1.0], precision])
    recall = np.concatenate([[0.0], recall])
    thr = np.concatenate([[np.inf], thr])
    trapezoid = getattr(np, "trapezoid", None) or np.trapz  # numpy < 2 names it trapz
    auc_pr = float(trapezoid(precision, recall))
    return PRCurve(precision, recall, thr), auc_pr


def recall_at_100_precision(curve: PRCurve) -> float:
    """Largest recall at which precision is exactly 1 (0 when the best match is already wrong)."""
    return recall_at_precision(curve, 1.0)


def recall_at_precision(curve: PRCurve, precision: float) -> float:
    """Largest recall at which precision is at least ``precision`` (R@99P: 0.99). 0 when no
    point reaches it."""
    # a hair of slack so that 99/100 accepted counts at 0.99 despite float division
    reached = curve.precision >= float(precision) - 1e-12
    return float(curve.recall[reached].max()) if reached.any() else 0.0


def precision_at_max_recall(curve: PRCurve) -> float:
    """Precision at the largest recall reached (best precision among points reaching it).

    The synthetic start point (threshold +inf) is excluded, so a curve that never recalls
    anything reports the precision of accepting every query (0), not the start's 1.
    """
    real = np.isfinite(curve.thresholds)
    if not real.any():
        return 0.0
    recall, precision = curve.recall[real], curve.precision[real]
    at_max = recall == recall.max()
    return float(precision[at_max].max())


def recall_at_n(correct_topk: np.ndarray, ns=DEFAULT_NS, over: np.ndarray | None = None) -> dict[int, float]:
    """Recall@N: the fraction of queries with at least one correct reference among their top N.

    ``correct_topk`` is (Q, k) bool, best first. ``over`` selects the queries in the denominator
    (recall-over-queries: those with a true match); None = all queries (VPR-Bench). N larger than
    k (k = number of references when fewer than N) uses all k candidates.
    """
    correct_topk = np.asarray(correct_topk, dtype=bool)
    if over is not None:
        correct_topk = correct_topk[np.asarray(over, dtype=bool)]
    if len(correct_topk) == 0:
        raise DataError("no query has a true match in the ground truth, so Recall@N is undefined")
    found = np.logical_or.accumulate(correct_topk, axis=1)
    return {int(n): float(found[:, min(int(n), found.shape[1]) - 1].mean()) for n in ns}


# ---------------------------------------------------------------------------- protocols
@dataclass(frozen=True)
class Accepted:
    """What an acceptance rule named ``rule`` made of each query's candidates: one score per query
    (``scores``, (Q,); -inf = rejected) and the reference index it vouches for (``matches``, (Q,))."""

    scores: np.ndarray | None
    matches: np.ndarray | None
    rule: str = "raw"


def evaluate_retrieval(
    retrieved: np.ndarray,
    scores: np.ndarray,
    ground_truth: GroundTruth,
    protocol: str = RECALL_OVER_QUERIES,
    thresholds: int | None = None,
    ns=DEFAULT_NS,
    accepted: Accepted | None = None,
) -> Metrics:
    """All metrics from ranked candidates: ``retrieved``/``scores`` (Q, k) best first, k >= max(ns)
    (or all references). ``thresholds`` applies to ``recall-over-queries`` only.

    ``accepted``: the PR curve thresholds its scores, and a query is correct when its accepted
    match is (None: the best-match similarity and the best match, rule ``raw``)."""
    acceptance_scores, accepted_matches = (None, None) if accepted is None else (accepted.scores, accepted.matches)
    acceptance = "raw" if accepted is None else accepted.rule
    if protocol not in PROTOCOLS:
        raise DataError(f"unknown protocol {protocol!r}; choose one of {', '.join(PROTOCOLS)}")
    retrieved = np.asarray(retrieved)
    scores = np.asarray(scores, dtype=np.float64)
    if retrieved.ndim == 1:
        retrieved, scores = retrieved[:, None], scores[:, None]
    if retrieved.shape != scores.shape:
        raise DataError(f"retrieved indices {retrieved.shape} and scores {scores.shape} differ in shape")
    if retrieved.shape[0] != ground_truth.num_queries:
        raise DataError(
            f"ground truth has {ground_truth.num_queries} queries but {retrieved.shape[0]} " f"were matched"
        )
    if not np.isfinite(scores[:, 0]).all():
        raise DataError("best-match scores contain NaN or infinite values")
    has_match = ground_truth.has_match
    if not has_match.any():
        raise DataError(
            f"no query has a true match in the ground truth ({ground_truth.description}): " f"nothing to evaluate"
        )
    correct = ground_truth.correct_mask(retrieved)
    top1_scores, top1_correct = scores[:, 0], correct[:, 0]
    pr_scores, pr_correct = _acceptance(top1_scores, top1_correct, ground_truth, acceptance_scores, accepted_matches)
    notes = []
    n_without = int((~has_match).sum())
    if protocol == VPRBENCH:
        if thresholds is not None:
            raise DataError(
                "--thresholds applies to the recall-over-queries protocol only; "
                "vprbench uses every top-1 score, as VPR-Bench does"
            )
        rejected = ~np.isfinite(pr_scores)
        if rejected.any():
            # every query is on VPR-Bench's curve: a rejected one sorts below all others
            low = pr_scores[~rejected].min() - 1.0 if (~rejected).any() else 0.0
            pr_scores = np.where(rejected, low, pr_scores)
        curve, auc_pr = pr_curve_vprbench(pr_scores, pr_correct)
        recalls = recall_at_n(correct, ns, over=None)
        if n_without:
            notes.append(f"{n_without} queries have no true match; they count as misses in Recall@N")
        if not top1_correct.any():
            notes.append("no top-1 match is correct: VPR-Bench's recall is undefined; reported AUC 0")
    else:
        curve, auc_pr = pr_curve_over_queries(pr_scores, pr_correct, has_match, thresholds)
        recalls = recall_at_n(correct, ns, over=has_match)
        if n_without:
            notes.append(
                f"{n_without} queries have no true match; excluded from recall's denominator, "
                f"their best matches count as false positives"
            )
    return Metrics(
        protocol=protocol,
        num_queries=int(ground_truth.num_queries),
        num_queries_with_match=int(has_match.sum()),
        recall_at_100_precision=recall_at_100_precision(curve),
        recall_at_99_precision=recall_at_precision(curve, 0.99),
        recall_at_95_precision=recall_at_precision(curve, 0.95),
        precision_at_max_recall=precision_at_max_recall(curve),
        auc_pr=auc_pr,
        recall_at_n=recalls,
        top1_accuracy=float(top1_correct.mean()),
        curve=curve,
        thresholds="exact" if thresholds is None or protocol == VPRBENCH else f"{int(thresholds)} uniform",
        notes=notes,
        acceptance=acceptance,
    )


def _acceptance(top1_scores, top1_correct, ground_truth, acceptance_scores, accepted_matches):
    """The (scores, correct) pairs the PR curve thresholds: the best match's, or an acceptance
    rule's scores with the correctness of the matches it accepted."""
    if acceptance_scores is None and accepted_matches is None:
        return top1_scores, top1_correct
    if acceptance_scores is None or accepted_matches is None:
        raise DataError("acceptance scores and accepted matches go together; got only one of them")
    pr_scores = np.asarray(acceptance_scores, dtype=np.float64)
    matches = np.asarray(accepted_matches)
    if pr_scores.shape != top1_scores.shape or matches.shape != top1_scores.shape:
        raise DataError(
            f"acceptance scores {pr_scores.shape} and matches {matches.shape} must hold one value per "
            f"query ({top1_scores.shape[0]})"
        )
    if np.isnan(pr_scores).any() or np.isposinf(pr_scores).any():
        raise DataError("acceptance scores contain NaN or +inf (only -inf, a rejection, is allowed)")
    return pr_scores, ground_truth.correct_mask(matches[:, None])[:, 0]


def evaluate_similarity(
    similarity: np.ndarray,
    ground_truth: GroundTruth,
    protocol: str = RECALL_OVER_QUERIES,
    thresholds: int | None = None,
    ns=DEFAULT_NS,
) -> Metrics:
    """All metrics from a full (Q, R) similarity matrix (higher = more similar)."""
    s = np.asarray(similarity)
    if s.ndim != 2:
        raise DataError(f"similarity must be a 2-D (queries x references) matrix, got shape {s.shape}")
    if s.shape != (ground_truth.num_queries, ground_truth.num_references):
        raise DataError(
            f"similarity matrix is {s.shape[0]} x {s.shape[1]} but the ground truth is for "
            f"{ground_truth.num_queries} queries x {ground_truth.num_references} references"
        )
    retrieved, scores = top_k_of_matrix(s, max(ns))
    return evaluate_retrieval(retrieved, scores, ground_truth, protocol, thresholds, ns)
