"""Evaluation: the experiment runner, reports and plots, over the metrics of :mod:`fdnet.metrics`
(pure functions under named protocols, re-exported here).

``experiment`` runs a
descriptor on an :class:`~fdnet.data.split.EvaluationSplit`; ``report`` prints tables and writes
JSON; ``plots`` draws PR curves, similarity matrices and example matches (matplotlib, imported
only when plotting).
"""

from fdnet.metrics import (
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
