"""``fdnet match``'s work: describe a reference map and queries, rank the map's images for each
query (:mod:`fdnet.matching.search`), decide with an acceptance rule or a calibration
(:mod:`fdnet.decisions`), and write the ranked-candidates CSV and hloc's retrieval pairs file
(:func:`retrieval_pairs`: names relative to the folder holding the reference and query folders,
hloc's ``image_dir``). Images are
listed in fdnet's one order (:func:`fdnet.data.images.list_images`), and every row carries both
the indices and the images' names (:func:`fdnet.data.images.image_name`: the absolute path as
listed, the name every output gives an image)."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from fdnet.data.images import image_name
from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.errors import ConfigError
from fdnet.matching.search import SearchSettings, index_settings, rank_references, reference_times_and_positions
from fdnet.matching.sequence import check_sequence_length

logger = logging.getLogger(__name__)

MATCH_COLUMNS = ["query_index", "query", "rank", "reference_index", "reference", "score"]


@dataclass
class MatchSummary:
    """What :func:`match_images` wrote."""

    out: str
    method: str
    num_references: int
    num_queries: int
    top_k: int
    #: with a calibration: the calibration and how many queries it accepted
    calibration: object = None
    accepted: int | None = None
    #: with pairs_out: hloc's pairs file, how many pairs it holds and the folder their names are relative to
    pairs_out: str | None = None
    num_pairs: int | None = None
    pairs_root: str | None = None


@dataclass(frozen=True)
class MatchRequest:
    """What ``fdnet match`` was asked: the ``reference`` folder (the map) and the ``query``
    folder; ``out``: the ranked-candidates CSV (None: none, when ``pairs_out`` is given);
    ``top_k``; the search (``index``, ``index_set`` as KEY=VALUE, ``index_file``,
    ``sequence_length``); the decision (``calibration``, a file or run directory from
    ``fdnet calibrate``, which adds ``acceptance_score`` and ``accepted`` columns; or ``accept``,
    an AcceptanceSpec, which adds the rule's ``acceptance_score`` alone); ``pairs_out`` (hloc's
    pairs file; ``pairs_accepted_only``: only the accepted pairs); ``inputs``: (option, path) of
    the files the method reads (``--vectors``, ``--weights``, ...), which no output may be;
    ``pipeline``: how images are decoded and described."""

    reference: str
    query: str
    out: str | None = None
    top_k: int = 5
    index: str = "exact"
    index_set: tuple = ()
    index_file: str | None = None
    sequence_length: int = 1
    calibration: str | None = None
    accept: object = None
    pairs_out: str | None = None
    pairs_accepted_only: bool = False
    inputs: tuple = ()
    pipeline: PipelineSettings = field(default_factory=lambda: PipelineSettings(batch_size=64, progress=True))


def match_images(
    request: MatchRequest, make_descriptor: Callable[[], object], log: Callable[[str], None] | None = None
) -> MatchSummary:
    """Describe the reference folder (the map) and the query folder with the method
    ``make_descriptor()`` returns (called after the settings and output paths are checked, so a
    refusal comes before any model is loaded), rank the references of every query
    (:func:`rank_references`) and write the top ``top_k`` to the CSV (atomically) and hloc's pairs
    file (:func:`retrieval_pairs`); the CSV and the pairs file are renamed into place together,
    once both are written (a full disk leaves both as they were). ``log`` gets the index cache's
    messages (default: this module's logger)."""
    from fdnet.data.images import list_images

    r = request
    sequence_length, settings = _check_request(r)
    ref_paths, query_paths = list_images(r.reference), list_images(r.query)
    names = pair_names(r.reference, r.query, ref_paths, query_paths, r.pairs_out) if r.pairs_out is not None else None
    descriptor = make_descriptor()
    calibration, rule, depth = _decision_rule(r, descriptor, sequence_length, names)
    neighbourhood = reference_times_and_positions(ref_paths)
    if rule is not None:  # e.g. radius_m: image folders have no positions; refused before describing
        rule.check_available(
            {"images", *neighbourhood},
            "fdnet match (references without "
            + ("positions)" if "reference_times" in neighbourhood else "timestamps or positions)"),
        )
    if settings is not None and not descriptor.dot_product_similarity:
        raise ConfigError(
            f"method {descriptor.name!r} does not compare vectors by dot product, so a "
            "faiss index would rank by the wrong measure; use --index exact"
        )
    if descriptor.needs_fit:
        logger.info(f"{descriptor.name}: learning from the {len(ref_paths)} reference images (none supplied)")
        descriptor.fit(ref_paths)
    indices, scores = rank_references(
        descriptor,
        ref_paths,
        query_paths,
        depth,
        SearchSettings(settings, sequence_length, r.index_file),
        r.pipeline,
        log=log,
    )
    decision = accepted = None
    if rule is not None:
        from fdnet.decisions.acceptance import Candidates, decide

        candidates = Candidates(
            indices,
            scores,
            similarity_ceiling=float(descriptor.similarity_ceiling),
            query_paths=query_paths,
            reference_paths=ref_paths,
            **neighbourhood,
        )
        if calibration is not None:
            decision, accepted = calibration.decide(candidates)
        else:
            decision = decide(r.accept, candidates)
    ranked = RankedMatches(indices, scores, query_paths, ref_paths, decision, accepted)
    num_pairs = _write_outputs(r, ranked, names)
    return MatchSummary(
        out=None if r.out is None else str(r.out),
        method=descriptor.name,
        num_references=len(ref_paths),
        num_queries=len(query_paths),
        top_k=r.top_k,
        calibration=calibration,
        accepted=None if accepted is None else int(accepted.sum()),
        pairs_out=None if r.pairs_out is None else str(r.pairs_out),
        num_pairs=num_pairs,
        pairs_root=None if names is None else str(names[2]),
    )


@dataclass(frozen=True)
class RankedMatches:
    """Each query's ranked references (indices, scores; (Q, depth)) and, with a rule, its
    decision (acceptance scores) and which queries it accepted."""

    indices: np.ndarray
    scores: np.ndarray
    query_paths: list
    reference_paths: list
    decision: object = None
    accepted: np.ndarray | None = None


def _check_request(r: MatchRequest):
    """Refuse what cannot work before any image is read: (sequence length, faiss settings or None)."""
    from fdnet.io import ensure_writable

    if r.top_k < 1:
        raise ConfigError("--top-k must be at least 1")
    sequence_length = check_sequence_length(r.sequence_length)
    check_outputs(
        r.out,
        r.pairs_out,
        r.pairs_accepted_only,
        r.calibration is not None or r.accept is not None,
        index_file=r.index_file,
        inputs=[
            *r.inputs,
            ("--reference", r.reference),
            ("--query", r.query),
            *([("--calibration", r.calibration)] if r.calibration else []),
        ],
    )
    settings = index_settings(r.index, r.index_set, r.index_file, sequence_length)
    for path, what in ((r.out, "matches CSV"), (r.pairs_out, "pairs file"), (r.index_file, "index file")):
        if path is not None:
            ensure_writable(path, what=what)  # before describing every image, not after
    return sequence_length, settings


def _decision_rule(r: MatchRequest, descriptor, sequence_length: int, names):
    """(the loaded calibration or None, the rule deciding or None, how many candidates to rank)."""
    depth = r.top_k if r.accept is None else max(r.top_k, r.accept.depth)
    calibration = None
    if r.calibration is not None:
        from fdnet.decisions.calibration import load_calibration

        calibration = load_calibration(r.calibration)
        calibration.check(descriptor, sequence_length=sequence_length, source=r.calibration)
        depth = max(r.top_k, calibration.spec.depth)  # the rule may need more candidates than are written
    if names is not None and not r.pairs_accepted_only and set(names[0]) & set(names[1]):
        depth = max(depth, r.top_k + 1)  # a query that is also a reference: its pairs skip itself
    rule = r.accept if r.accept is not None else (calibration.spec if calibration is not None else None)
    return calibration, rule, depth


def _write_outputs(r: MatchRequest, ranked: RankedMatches, names) -> int | None:
    """Write the CSV and the pairs file, both or neither (renamed over their targets at the end);
    the number of pairs written (None without a pairs file)."""
    import contextlib

    from fdnet.io import atomic_path

    num_pairs = None
    with contextlib.ExitStack() as outputs:
        if r.pairs_out is not None:
            from fdnet.descriptors.hloc_formats import write_pairs_to

            tmp = outputs.enter_context(atomic_path(r.pairs_out))
            with open(tmp, "w", encoding="utf-8", newline="\n") as handle:
                pairs = retrieval_pairs(
                    ranked.indices, names[1], names[0], r.top_k, ranked.decision, ranked.accepted, r.pairs_accepted_only
                )
                num_pairs = write_pairs_to(handle, pairs, r.pairs_out)
        if r.out is not None:
            tmp = outputs.enter_context(atomic_path(r.out))
            tmp.write_text(
                matches_text(
                    ranked.indices,
                    ranked.scores,
                    ranked.query_paths,
                    ranked.reference_paths,
                    r.top_k,
                    ranked.decision,
                    ranked.accepted,
                ),
                encoding="utf-8",
                errors="surrogateescape",
            )
    return num_pairs


def _same_path(a, b) -> bool:
    """Whether ``a`` and ``b`` name one file (after ``.``, ``..`` and symbolic links)."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one does not exist yet
        return os.path.realpath(a) == os.path.realpath(b)


def check_outputs(out, pairs_out, pairs_accepted_only: bool, has_rule: bool, index_file=None, inputs=()) -> None:
    """Refuse output settings that cannot work, before any work: no output at all, one file for
    two outputs (``--out``, ``--pairs-out``, ``--index-file``), an output that is a file the
    command reads (``inputs``: (option, path); writing it would destroy it), accepted pairs
    without a rule to accept them or without a pairs file."""
    if out is None and pairs_out is None:
        raise ConfigError("give --out matches.csv, --pairs-out pairs.txt, or both")
    written = [
        (option, path)
        for option, path in (("--out", out), ("--pairs-out", pairs_out), ("--index-file", index_file))
        if path is not None
    ]
    for i, (option, path) in enumerate(written):
        for other, other_path in written[:i]:
            if _same_path(path, other_path):
                raise ConfigError(f"{other} and {option} are the same file {path}; give two names")
        for given, source in inputs:
            if source is not None and _same_path(path, source):
                raise ConfigError(
                    f"{option} {path} is the {given} file {source}: writing it would destroy what the "
                    "command reads; give another name"
                )
    if pairs_accepted_only and pairs_out is None:
        raise ConfigError("--pairs-accepted-only needs --pairs-out FILE")
    if pairs_accepted_only and not has_rule:
        raise ConfigError(
            "--pairs-accepted-only needs a decision: --calibration FILE|RUN_DIR (or one stored in the "
            "run) or --accept RULE"
        )


def pair_names(reference, query, ref_paths, query_paths, where) -> tuple[list[str], list[str], Path]:
    """(reference names, query names, root): the images' names in hloc's pairs file, their paths
    relative to ``root``, the deepest folder holding the reference and query folders (a video's
    or bag's: the folder holding it), which is hloc's ``image_dir``. A name hloc's pairs file
    cannot hold (whitespace) is refused here, before any image is described."""
    from fdnet.descriptors.hloc_formats import check_pair_name, image_root, relative_names

    root = image_root([reference, query])
    ref_names = [check_pair_name(n, where) for n in relative_names(ref_paths, root)]
    query_names = [check_pair_name(n, where) for n in relative_names(query_paths, root)]
    return ref_names, query_names, root


def retrieval_pairs(
    indices, query_names, ref_names, top_k: int, decision=None, accepted=None, accepted_only: bool = False
):
    """hloc's retrieval pairs ``(query name, reference name)``, query by query in order, best
    reference first: each query's ``top_k`` references (the rows of the matches CSV), or with
    ``accepted_only`` the one match the decision accepts (a calibrated decision: where
    ``accepted``; a rule without a threshold: every match no gate rejected, score above -inf);
    none for a new place. A query is never paired with itself (the same name on both sides, when
    the query folder is the reference folder); its next reference takes the place, as in hloc's
    ``pairs_from_retrieval``."""
    for q, row in enumerate(indices):
        if accepted_only:
            match = int(decision.match[q])
            taken = bool(accepted[q]) if accepted is not None else bool(np.isfinite(decision.score[q]))
            chosen = [match] if taken and match >= 0 else []
        else:
            chosen = [int(i) for i in row if i >= 0 and ref_names[i] != query_names[q]][:top_k]
        for i in chosen:
            if ref_names[i] != query_names[q]:
                yield query_names[q], ref_names[i]


def decision_columns(decision=None, accepted=None) -> list[str]:
    """The columns a decision adds to a ranked-candidates CSV (``fdnet match``, ``database
    query``): ``acceptance_score`` with a rule's decision, ``accepted`` with a calibrated one."""
    return ([] if decision is None else ["acceptance_score"]) + ([] if accepted is None else ["accepted"])


def decision_cells(q: int, chosen: bool, decision=None, accepted=None) -> list:
    """Query ``q``'s cells under :func:`decision_columns` on one row (``chosen``: the row of the
    match the calibrated rule accepted)."""
    return ([] if decision is None else [f"{decision.score[q]:.6f}"]) + ([] if accepted is None else [int(chosen)])


def matches_text(indices, scores, query_paths, ref_paths, top_k: int, decision=None, accepted=None) -> str:
    """The ranked-candidates CSV: :data:`MATCH_COLUMNS`, plus ``acceptance_score`` with a
    ``decision`` and ``accepted`` with a calibrated one. Rows beyond ``top_k`` appear only for
    the match a rule accepted (a re-ranking rule may pick it)."""
    import csv
    import io

    from fdnet.io import spreadsheet_text

    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(MATCH_COLUMNS + decision_columns(decision, accepted))
    for q, (row_i, row_s) in enumerate(zip(indices, scores)):
        for rank, (i, s) in enumerate(zip(row_i, row_s), start=1):
            chosen = accepted is not None and i == decision.match[q] and bool(accepted[q])
            if i >= 0 and (rank <= top_k or chosen):
                row = [
                    q,
                    spreadsheet_text(image_name(query_paths[q])),
                    rank,
                    int(i),
                    spreadsheet_text(image_name(ref_paths[i])),
                    f"{float(s):.6f}",
                ]
                writer.writerow(row + decision_cells(q, chosen, decision, accepted))
    return buffer.getvalue()
