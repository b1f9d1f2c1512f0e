"""Run one descriptor on one evaluation split and measure it: the experiment runner.

The pipeline, for any method (only the :class:`~fdnet.descriptors.base.Descriptor` interface is
used, never a method's name):

1. ``descriptor.fit(reference paths)`` when ``descriptor.needs_fit`` (e.g. a DBoW vocabulary
   learnt on the map; reported, because it means the method saw the map before matching);
2. describe reference and query images through the streaming pipeline (``describe_paths``:
   decoding in worker processes overlapped with the model, a few batches of images in memory),
   timing the model only: ms/image over references and queries together;
3. rank references for every query by ``descriptor.similarity`` -- blocked top-k
   (:func:`fdnet.matching.similarity.top_k`) so no (Q, R) matrix is needed -- timing it as
   ms/query. Sequence matching uses the full matrix when it is small (at most
   ``MAX_MATRIX_ENTRIES``) and blocks of query rows beyond
   (:func:`fdnet.matching.sequence.sequence_top_k`, the same numbers); the full matrix is only
   ever kept when asked (``keep_similarity``, for plots) and small;
4. acceptance scores under each requested rule (:mod:`fdnet.decisions.acceptance`: ``raw``,
   ``margin``...; the candidates retrieved are at least as many as the rules need, e.g. 2r + 2
   for a margin of radius r), on the sequence candidates when sequence matching is on;
5. metrics under each requested protocol and rule (:mod:`fdnet.metrics`), which need
   only each query's ranked top-N, their scores and the acceptance scores.

Results of a precomputed similarity matrix (no descriptor) use :func:`evaluate_matrix`, so the
report and plots treat both alike.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from fdnet.data.groundtruth import GroundTruth
from fdnet.data.split import EvaluationSplit
from fdnet.decisions.acceptance import AcceptanceSpec, Candidates, Decision, decide, parse_acceptance
from fdnet.descriptors.base import Descriptor, describe_paths
from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.errors import DataError
from fdnet.matching.similarity import similarity_matrix, top_k
from fdnet.metrics import (
    DEFAULT_NS,
    RECALL_OVER_QUERIES,
    Accepted,
    Metrics,
    evaluate_retrieval,
    top_k_of_matrix,
)

#: largest Q x R matrix kept for plots (float32: 400 MB); larger maps are ranked blockwise only
MAX_MATRIX_ENTRIES = 100_000_000


@dataclass
class MethodResult:
    """One method on one split: metrics per protocol plus what is needed to report and plot.

    ``metrics`` (per protocol) are under the first acceptance rule asked for; ``by_acceptance``
    holds every rule's (rule expression -> protocol -> Metrics), ``decisions`` every rule's
    acceptance scores and matches."""

    method: str
    metrics: dict[str, Metrics]
    retrieved: np.ndarray
    scores: np.ndarray
    ground_truth: GroundTruth
    settings: dict = field(default_factory=dict)
    dataset: str = ""
    timing: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    similarity: np.ndarray | None = None
    query_paths: list[Path] | None = None
    reference_paths: list[Path] | None = None
    by_acceptance: dict[str, dict[str, Metrics]] = field(default_factory=dict)
    decisions: dict[str, Decision] = field(default_factory=dict)

    @property
    def protocols(self) -> list[str]:
        return list(self.metrics)

    @property
    def acceptance_rules(self) -> list[str]:
        return list(self.by_acceptance) or [next(iter(self.metrics.values())).acceptance]

    def to_dict(self, protocol: str | None = None, include_curve: bool = True) -> dict:
        """The JSON object of this result under ``protocol`` (default: the first evaluated).

        Keys: ``method``, ``protocol``, ``num_queries``, ``recall_at_100_precision``,
        ``precision_at_max_recall``, ``auc_pr``, ``recall_at_n`` ({"1", "5", "10", "20"}),
        ``top1_accuracy``, ``protocol_definition``, ``thresholds``, ``num_queries_with_match``,
        ``num_references``, ``dataset``, ``ground_truth``, ``settings``, ``timing``
        (``ms_per_image``, ``ms_per_query``...), ``notes`` and ``pr_curve``; ``acceptance`` names
        the rule the PR numbers (R@100P, R@99P, R@95P, P@maxR, AUC-PR, the curve) use. With several
        rules, those top-level numbers are the first rule's and ``per_acceptance`` maps every rule
        to its own numbers (and settings).
        """
        protocol = protocol or self.protocols[0]
        m = self.metrics[protocol].to_dict(include_curve=False)
        out = {
            "method": self.method,
            **m,
            "num_references": int(self.ground_truth.num_references),
            "dataset": self.dataset,
            "ground_truth": self.ground_truth.description,
            "settings": self.settings,
            "timing": self.timing,
        }
        notes = self.notes + m.pop("notes", [])
        out.pop("notes", None)
        if notes:
            out["notes"] = notes
        if include_curve:
            out["pr_curve"] = self.metrics[protocol].curve.to_dict()
        rule = self.metrics[protocol].acceptance
        if rule in self.decisions:
            out["acceptance_settings"] = self.decisions[rule].settings
        if len(self.by_acceptance) > 1:
            out["per_acceptance"] = {
                name: _pr_summary(per[protocol], self.decisions.get(name), include_curve)
                for name, per in self.by_acceptance.items()
            }
        return out


def _pr_summary(m: Metrics, decision: Decision | None, include_curve: bool) -> dict:
    out = {
        "recall_at_100_precision": m.recall_at_100_precision,
        "recall_at_99_precision": m.recall_at_99_precision,
        "recall_at_95_precision": m.recall_at_95_precision,
        "precision_at_max_recall": m.precision_at_max_recall,
        "auc_pr": m.auc_pr,
    }
    if decision is not None:
        out["settings"] = decision.settings
    if include_curve:
        out["pr_curve"] = m.curve.to_dict()
    return out


def _acceptance_specs(acceptance) -> list[AcceptanceSpec]:
    """None -> [raw]; strings are parsed with their default settings."""
    if not acceptance:
        return [parse_acceptance("raw")]
    return [parse_acceptance(a) if isinstance(a, str) else a for a in acceptance]


@dataclass(frozen=True)
class ScoringSettings:
    """How ranked candidates are scored: the named metric ``protocols``, the recall-over-queries
    sweep's ``thresholds`` (None = exact, 500 = the paper's), the recall@N cut-offs ``ns``, and the
    ``acceptance`` rules whose scores the PR curve thresholds (None = ``raw``; the first gives
    ``metrics``)."""

    protocols: Sequence[str] = (RECALL_OVER_QUERIES,)
    thresholds: int | None = None
    ns: Sequence[int] = DEFAULT_NS
    acceptance: Sequence[AcceptanceSpec | str] | None = None


def _decide_and_score(retrieved, scores, gt, scoring: ScoringSettings, candidates_context, timing=None):
    """(metrics of the first rule, by_acceptance, decisions) for ranked candidates. ``timing``, when
    given, gets ``acceptance_ms_per_query``: each rule's wall time over the queries (what a rule
    that looks at images, e.g. geometric verification, costs; a later rule reusing an earlier
    one's verified pairs costs less)."""
    specs = _acceptance_specs(scoring.acceptance)
    candidates = Candidates(retrieved, scores, **candidates_context)
    by_acceptance: dict[str, dict[str, Metrics]] = {}
    decisions: dict[str, Decision] = {}
    for spec in specs:
        t0 = time.perf_counter()
        decision = decide(spec, candidates)
        if timing is not None:
            timing.setdefault("acceptance_ms_per_query", {})[spec.name] = (
                1000.0 * (time.perf_counter() - t0) / max(candidates.num_queries, 1)
            )
        decisions[spec.name] = decision
        by_acceptance[spec.name] = _metrics(retrieved, scores, gt, scoring, decision)
    return by_acceptance[specs[0].name], by_acceptance, decisions


def _metrics(retrieved, scores, gt, scoring: ScoringSettings, decision: Decision | None = None) -> dict[str, Metrics]:
    accepted = None if decision is None else Accepted(decision.score, decision.match, decision.rule)
    return {
        p: evaluate_retrieval(
            retrieved,
            scores,
            gt,
            p,
            thresholds=scoring.thresholds if p == RECALL_OVER_QUERIES else None,
            ns=scoring.ns,
            accepted=accepted,
        )
        for p in scoring.protocols
    }


def _rank(
    descriptor: Descriptor, queries, refs, k: int, sequence_length: int, keep_similarity: bool, max_matrix_entries: int
):
    """(the top ``k`` references of each query, their scores, the (Q, R) similarity matrix or
    None, the matching timing, notes): by sequence similarity when ``sequence_length`` > 1; the
    matrix when it fits in ``max_matrix_entries`` and is wanted."""
    timing: dict = {}
    notes: list[str] = []
    small = len(queries) * len(refs) <= max_matrix_entries
    similarity = None
    t0 = time.perf_counter()
    if sequence_length > 1 and small:
        from fdnet.matching.sequence import sequence_similarity

        similarity = sequence_similarity(similarity_matrix(queries, refs, descriptor.similarity), sequence_length)
        retrieved, scores = top_k_of_matrix(similarity, k)
    elif sequence_length > 1:
        from fdnet.matching.sequence import sequence_top_k

        retrieved, scores = sequence_top_k(queries, refs, k, sequence_length, similarity=descriptor.similarity)
    else:
        retrieved, scores = top_k(queries, refs, k, similarity=descriptor.similarity)
    timing["ms_per_query"] = 1000.0 * (time.perf_counter() - t0) / max(len(queries), 1)
    timing["num_references"] = len(refs)
    timing["num_queries"] = len(queries)
    if sequence_length > 1:
        notes.append(f"ranked by SeqSLAM sequence similarity over {sequence_length} consecutive queries")

    if keep_similarity and similarity is None:
        if small:
            similarity = similarity_matrix(queries, refs, descriptor.similarity)
        else:
            notes.append(f"similarity matrix not kept for plots ({len(queries)} x {len(refs)} is too large)")
    return retrieved, scores, similarity, timing, notes


def evaluate_method(
    descriptor: Descriptor,
    split: EvaluationSplit,
    scoring: ScoringSettings | None = None,
    pipeline: PipelineSettings | None = None,
    sequence_length: int = 1,
    keep_similarity: bool = False,
    log: Callable[[str], None] | None = None,
    max_matrix_entries: int = MAX_MATRIX_ENTRIES,
) -> MethodResult:
    """Describe, match and score ``descriptor`` on ``split`` (see the module docstring).

    ``scoring``: :class:`ScoringSettings` (default: recall over queries, exact, the raw rule);
    ``pipeline``: how images are decoded and described (default: batches of 64, no progress
    bar); ``sequence_length`` > 1 ranks by SeqSLAM sequence similarity
    (:func:`fdnet.matching.sequence.sequence_similarity`; in blocks of query rows beyond
    ``max_matrix_entries``); ``keep_similarity`` keeps the (Q, R) matrix on the result for plots
    (skipped, with a note, beyond ``max_matrix_entries``).
    """
    scoring = scoring or ScoringSettings()
    pipeline = pipeline or PipelineSettings(batch_size=64)
    batch_size, progress, workers = pipeline.batch_size, pipeline.progress, pipeline.workers
    specs = _acceptance_specs(scoring.acceptance)
    say = log or (lambda message: None)
    ref_paths, query_paths = list(split.reference.paths), list(split.query.paths)
    for spec in specs:  # e.g. images too small for geometric verification: say so before describing
        spec.check_available({"images"}, "evaluation on image folders")
        spec.check_images(query_paths, ref_paths)
    notes: list[str] = []
    timing: dict = {}

    if descriptor.needs_fit:
        say(f"{descriptor.name}: fitting on the {len(ref_paths)} reference images before matching")
        t0 = time.perf_counter()
        descriptor.fit(ref_paths)
        timing["seconds_fit"] = time.perf_counter() - t0
        notes.append(f"fitted on the {len(ref_paths)} reference images of this split")

    ref_timing: dict = {}
    query_timing: dict = {}
    refs = describe_paths(descriptor, ref_paths, batch_size, progress=progress, timing=ref_timing, workers=workers)
    queries = describe_paths(
        descriptor, query_paths, batch_size, progress=progress, timing=query_timing, workers=workers
    )
    num_images = ref_timing["num_images"] + query_timing["num_images"]
    seconds_describe = ref_timing["seconds_describe"] + query_timing["seconds_describe"]
    timing["ms_per_image"] = 1000.0 * seconds_describe / max(num_images, 1)

    k = max(max(scoring.ns), *(spec.depth for spec in specs))
    retrieved, scores, similarity, rank_timing, rank_notes = _rank(
        descriptor, queries, refs, k, sequence_length, keep_similarity, max_matrix_entries
    )
    timing.update(rank_timing)
    notes.extend(rank_notes)

    settings = dict(descriptor.settings())
    settings.setdefault("dim", int(descriptor.dim))
    if sequence_length > 1:
        settings["sequence_length"] = int(sequence_length)
    context = {
        "similarity_ceiling": float(descriptor.similarity_ceiling),
        "query_paths": query_paths,
        "reference_paths": ref_paths,
    }
    metrics, by_acceptance, decisions = _decide_and_score(
        retrieved, scores, split.ground_truth, scoring, context, timing
    )
    return MethodResult(
        method=descriptor.name,
        metrics=metrics,
        by_acceptance=by_acceptance,
        decisions=decisions,
        retrieved=retrieved,
        scores=scores,
        ground_truth=split.ground_truth,
        settings=settings,
        dataset=split.description,
        timing=timing,
        notes=notes,
        similarity=similarity if keep_similarity else None,
        query_paths=query_paths,
        reference_paths=ref_paths,
    )


def evaluate_matrix(
    similarity: np.ndarray,
    ground_truth: GroundTruth,
    method: str,
    scoring: ScoringSettings | None = None,
    dataset: str = "",
    query_paths: Sequence[Path] | None = None,
    reference_paths: Sequence[Path] | None = None,
    similarity_ceiling: float = 1.0,
) -> MethodResult:
    """A precomputed (Q, R) similarity matrix (higher = more similar) as a :class:`MethodResult`.
    ``scoring`` as for :func:`evaluate_method`; ``similarity_ceiling`` the largest similarity
    the matrix's method can produce (for the ``ratio`` rule)."""
    scoring = scoring or ScoringSettings()
    s = np.asarray(similarity)
    if s.shape != (ground_truth.num_queries, ground_truth.num_references):
        raise DataError(
            f"similarity matrix is {s.shape[0]} x {s.shape[1]} but the ground truth is for "
            f"{ground_truth.num_queries} queries x {ground_truth.num_references} references"
        )
    specs = _acceptance_specs(scoring.acceptance)
    for spec in specs:
        spec.check_available(
            {"images"} if query_paths is not None and reference_paths is not None else set(), "a similarity matrix"
        )
    retrieved, scores = top_k_of_matrix(s, max(max(scoring.ns), *(spec.depth for spec in specs)))
    context = {
        "similarity_ceiling": float(similarity_ceiling),
        "query_paths": None if query_paths is None else [Path(p) for p in query_paths],
        "reference_paths": None if reference_paths is None else [Path(p) for p in reference_paths],
    }
    metrics, by_acceptance, decisions = _decide_and_score(retrieved, scores, ground_truth, scoring, context)
    return MethodResult(
        method=method,
        metrics=metrics,
        by_acceptance=by_acceptance,
        decisions=decisions,
        retrieved=retrieved,
        scores=scores,
        ground_truth=ground_truth,
        settings={"source": "precomputed similarity matrix"},
        dataset=dataset,
        similarity=s,
        query_paths=None if query_paths is None else [Path(p) for p in query_paths],
        reference_paths=None if reference_paths is None else [Path(p) for p in reference_paths],
    )
