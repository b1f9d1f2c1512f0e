"""`fdnet match`: rank reference images (the map) for each query image (:func:`fdnet.tasks.match.match_images`).

Images are listed in fdnet's one order (:func:`fdnet.data.images.list_images`: natural order of
file names), and every output row carries both the indices and the file names.

``--index`` picks the search: ``exact`` (blocked numpy top-k, any method), or a faiss index for
dot-product methods (``flat`` exact, ``ivf``, ``ivfpq``, ``hnsw`` approximate, for maps of
10^5-10^6 places; :mod:`fdnet.matching.index`). ``--index-file FILE`` keeps the built index: a
later run with the same method (fingerprint), reference images and build settings loads it
instead of describing the map again.

``--calibration FILE|RUN_DIR`` (from ``fdnet calibrate``) adds a decision per query: the
calibrated acceptance rule's score (``acceptance_score``, on every row of the query) and
``accepted`` (1 on the row of the match the rule accepts when its score reaches the calibrated
threshold, else 0; a query without an accepted row is a new place). A calibration made for
another model (descriptor fingerprint) or another ``--sequence-length`` is refused. Without a
calibration, ``--accept RULE`` adds the rule's ``acceptance_score`` alone (no threshold, so no
``accepted``).

``--pairs-out FILE`` also writes hloc's retrieval pairs file (each query's top-k references, or
with ``--pairs-accepted-only`` the accepted match alone), the images named relative to the folder
holding the reference and query folders, hloc's ``image_dir``
(:func:`fdnet.tasks.match.retrieval_pairs`); ``--out`` may then be left out.
"""

from __future__ import annotations

from fdnet.cli.common import (
    acceptance_from_arguments,
    add_decision_arguments,
    add_device_argument,
    add_method_arguments,
    add_pipeline_arguments,
)
from fdnet.matching.search import INDEX_CHOICES


def register(sub) -> None:
    p = sub.add_parser(
        "match",
        help="match query images against a reference map; write ranked candidates with scores",
        description="Describe a reference folder (the map) and a query folder with one method, then "
        "write the top-k references per query (optionally with SeqSLAM sequence matching "
        "or a faiss index).",
    )
    p.add_argument("--reference", required=True, help="folder of reference (map) images")
    p.add_argument("--query", required=True, help="folder of query images")
    add_method_arguments(p)
    p.add_argument("--top-k", type=int, default=5, help="candidates per query (default 5)")
    p.add_argument(
        "--index",
        choices=INDEX_CHOICES,
        default="exact",
        help="exact blocked search (default, any method) or a faiss index (dot-product methods "
        "only): flat (exact), ivf (IVF-Flat), ivfpq (IVF-PQ, compressed), hnsw (graph)",
    )
    p.add_argument(
        "--index-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an index setting (repeatable): ivf_lists, ivf_probe, pq_bytes, refine, train_points, "
        "hnsw_neighbors, hnsw_ef_construction, hnsw_ef_search",
    )
    p.add_argument(
        "--index-file",
        metavar="FILE",
        help="keep the built faiss index in FILE (written atomically); when FILE holds the index of "
        "the same method, reference images and build settings, it is loaded and the map is "
        "not described again",
    )
    p.add_argument(
        "--sequence-length",
        type=int,
        default=1,
        help="SeqSLAM sequence matching over this many consecutive queries (1 = single images)",
    )
    add_decision_arguments(
        p,
        "a calibration from `fdnet calibrate` (YAML, or a run directory holding "
        "calibration.yaml): adds acceptance_score and accepted columns (accepted 1 = the "
        "revisit the calibrated rule accepts; none in a query = a new place)",
    )
    p.add_argument(
        "--out",
        help="CSV to write: query_index,query,rank,reference_index,reference,score (indices are "
        "positions in natural file-name order, names the images' absolute paths); needed unless "
        "--pairs-out is given",
    )
    p.add_argument(
        "--pairs-out",
        metavar="FILE",
        help="also write hloc's retrieval pairs file (cvg/Hierarchical-Localization, what its "
        "pairs_from_retrieval writes): 'query reference' per line, each query's --top-k references "
        "best first (a query never paired with itself), the images named by their paths relative "
        "to the deepest folder holding --reference and --query (a video's or bag's: the folder "
        "holding it), so hloc's image_dir is that folder; names holding whitespace are refused",
    )
    p.add_argument(
        "--pairs-accepted-only",
        action="store_true",
        help="with --pairs-out and a decision (--calibration, or --accept RULE): only the match the "
        "decision accepts, one pair per query and none for a new place (with --accept alone, which "
        "has no threshold: every query's match except those a gate rejects)",
    )
    add_pipeline_arguments(p)
    add_device_argument(p)
    p.set_defaults(func=run)


def input_files(args) -> list[tuple[str, str]]:
    """(option, path) of every file the method reads (``--vectors``, ``--weights``, ``--vocabulary``;
    a ``METHOD:PATH`` value's path), which no output may overwrite."""
    from fdnet.cli.common import method_labels, split_scope
    from fdnet.descriptors.registry import available_methods

    scopes = set(available_methods()) | set(method_labels(args))
    return [
        (f"--{option}", split_scope(value, scopes)[1])
        for option in ("vectors", "weights", "vocabulary")
        for value in getattr(args, option, None) or []
    ]


def run(args) -> int:
    import sys

    from fdnet.cli.common import check_pipeline_arguments, create_descriptor, method_options
    from fdnet.descriptors.pipeline import PipelineSettings
    from fdnet.tasks.match import MatchRequest, match_images

    check_pipeline_arguments(args)
    options = method_options(args, args.method)  # once: the descriptor and the run its calibration is in
    spec = acceptance_from_arguments(args)
    calibration = args.calibration
    if calibration is None and spec is None:
        # the one rule for stored calibrations: the run's (`fdnet calibrate --store-in-run`)
        from fdnet.decisions.calibration import stored_in_run

        stored = stored_in_run(options.get("checkpoint"))
        if stored is not None:
            calibration = str(stored)
            print(f"fdnet match: using the calibration stored in the run, {stored}", file=sys.stderr)
    request = MatchRequest(
        args.reference,
        args.query,
        args.out,
        top_k=args.top_k,
        index=args.index,
        index_set=tuple(args.index_set),
        index_file=args.index_file,
        sequence_length=args.sequence_length,
        calibration=calibration,
        accept=spec,
        pairs_out=args.pairs_out,
        pairs_accepted_only=args.pairs_accepted_only,
        inputs=tuple(input_files(args)),
        pipeline=PipelineSettings(batch_size=args.batch_size, workers=args.workers, progress=True),
    )
    summary = match_images(request, lambda: create_descriptor(args.method, args, options), log=print)
    if summary.out is not None:
        print(
            f"wrote {summary.out}: top-{summary.top_k} of {summary.num_references} references for "
            f"{summary.num_queries} queries ({summary.method})"
        )
    if summary.pairs_out is not None:
        what = "accepted pairs" if args.pairs_accepted_only else f"pairs (top-{summary.top_k} per query)"
        print(
            f"wrote {summary.pairs_out}: {summary.num_pairs} {what} for hloc, the images named relative to "
            f"{summary.pairs_root} (hloc's image_dir)"
        )
    if summary.calibration is not None:
        calibration = summary.calibration
        print(
            f"{summary.accepted} of {summary.num_queries} queries accepted by {calibration.rule} at threshold "
            f"{calibration.threshold:.6g} (it reached precision {calibration.precision:.3f} on "
            f"{calibration.accepted} accepted queries where it was measured; target "
            f"{calibration.target_precision:g}); the others are new places"
        )
    return 0
