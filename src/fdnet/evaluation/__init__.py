"""Evaluation: metrics under named protocols, the experiment runner, reports and plots.

``metrics`` is pure numpy (plus scikit-learn for the VPR-Bench protocol); ``experiment`` runs a
descriptor on an :class:`~fdnet.data.split.EvaluationSplit`; ``report`` prints tables and writes
JSON; ``plots`` draws PR curves, similarity matrices and example matches (matplotlib, imported
only when plotting).
"""

from fdnet.evaluation.metrics import (
    PROTOCOLS,
    RECALL_OVER_QUERIES,
    VPRBENCH,
    Metrics,
    PRCurve,
    evaluate_retrieval,
    evaluate_similarity,
)

__all__ = [
    "PROTOCOLS",
    "RECALL_OVER_QUERIES",
    "VPRBENCH",
    "Metrics",
    "PRCurve",
    "evaluate_retrieval",
    "evaluate_similarity",
]
