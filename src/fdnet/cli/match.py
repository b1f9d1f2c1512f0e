"""`fdnet match`: rank reference images (the map) for each query image.

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
"""

from __future__ import annotations

from fdnet.cli.common import (
    acceptance_from_arguments, add_decision_arguments, add_device_argument, add_method_arguments, add_pipeline_arguments,
)

INDEX_CHOICES = ["exact", "flat", "hnsw", "ivf", "ivfpq"]


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
    p.add_argument("--index", choices=INDEX_CHOICES, default="exact",
                   help="exact blocked search (default, any method) or a faiss index (dot-product methods "
                        "only): flat (exact), ivf (IVF-Flat), ivfpq (IVF-PQ, compressed), hnsw (graph)")
    p.add_argument("--index-set", action="append", default=[], metavar="KEY=VALUE",
                   help="an index setting (repeatable): ivf_lists, ivf_probe, pq_bytes, refine, train_points, "
                        "hnsw_neighbors, hnsw_ef_construction, hnsw_ef_search")
    p.add_argument("--index-file", metavar="FILE",
                   help="keep the built faiss index in FILE (written atomically); when FILE holds the index of "
                        "the same method, reference images and build settings, it is loaded and the map is "
                        "not described again")
    p.add_argument("--sequence-length", type=int, default=0,
                   help="SeqSLAM sequence matching over this many consecutive queries (0 = single image)")
    add_decision_arguments(p, "a calibration from `fdnet calibrate` (YAML, or a run directory holding calibration.yaml): "
                              "adds acceptance_score and accepted columns (accepted 1 = the revisit the calibrated "
                              "rule accepts; none in a query = a new place)")
    p.add_argument("--out", required=True,
                   help="CSV to write: query_index,query,rank,reference_index,reference,score (indices are "
                        "positions in natural file-name order, names the image file names)")
    add_pipeline_arguments(p)
    add_device_argument(p)
    p.set_defaults(func=run)


def _names_digest(paths) -> str:
    import hashlib
    import os

    digest = hashlib.sha256()
    for path in paths:
        digest.update(os.fsencode(path.name) + b"\0")  # the name's own bytes, UTF-8 or not
    return digest.hexdigest()


def _cached_index(path, descriptor, ref_paths, settings):
    """The index in ``path`` when it was built for this descriptor, these reference names and
    these build settings; else None (with the reason printed)."""
    from pathlib import Path

    from fdnet.matching.index import SEARCH_SETTINGS, VectorIndex

    if not Path(path).is_file():
        return None
    header = VectorIndex.read_header(path)
    meta = header.get("metadata", {})
    build = {k: v for k, v in vars(settings).items() if k not in SEARCH_SETTINGS}
    saved = {k: v for k, v in header["settings"].items() if k not in SEARCH_SETTINGS}
    reasons = []
    if meta.get("fingerprint") != descriptor.fingerprint():
        reasons.append("another method or model")
    if meta.get("references") != _names_digest(ref_paths) or header["count"] != len(ref_paths):
        reasons.append("other reference images")
    if saved != build:
        reasons.append(f"other build settings ({saved})")
    if reasons:
        print(f"{path}: holds an index of {', '.join(reasons)}; building a new one")
        return None
    return VectorIndex.load(path, search={k: getattr(settings, k) for k in SEARCH_SETTINGS})


def _reference_times_and_positions(paths) -> dict:
    """``reference_times`` (seconds) when every reference is a frame of a video or bag, and
    ``reference_positions`` (metres) when every one has a position (a bag's GPS/odometry): what
    the acceptance settings radius_s / radius_m need. Image files have neither."""
    import numpy as np

    from fdnet.data.sources import frame_records, positions_in_metres

    records = frame_records(paths)
    out = {}
    if records and all(r.timestamp is not None for r in records):
        out["reference_times"] = np.array([r.timestamp for r in records], dtype=np.float64)
    positions = positions_in_metres(records)
    if records and all(p is not None for p in positions):
        out["reference_positions"] = np.array(positions, dtype=np.float64)
    return out


def run(args) -> int:
    import csv
    import io
    import time

    from fdnet.cli.common import check_pipeline_arguments, create_descriptor
    from fdnet.data.images import list_images
    from fdnet.descriptors.base import describe_paths
    from fdnet.descriptors.pipeline import describe_stream
    from fdnet.errors import ConfigError
    from fdnet.io import atomic_write_text, ensure_writable, spreadsheet_text
    from fdnet.matching.index import VectorIndex, parse_index_settings
    from fdnet.matching.sequence import sequence_similarity
    from fdnet.matching.similarity import similarity_matrix, top_k, top_k_of_matrix

    if args.top_k < 1:
        raise ConfigError("--top-k must be at least 1")
    if args.sequence_length < 0:
        raise ConfigError(f"--sequence-length must be >= 0 (0 = single image), got {args.sequence_length}")
    check_pipeline_arguments(args)
    if args.index == "exact" and (args.index_set or args.index_file):
        raise ConfigError("--index-set and --index-file apply to the faiss indexes (--index flat|ivf|ivfpq|hnsw)")
    settings = parse_index_settings(args.index, args.index_set) if args.index != "exact" else None
    ensure_writable(args.out, what="matches CSV")  # before describing every image, not after
    if args.index_file:
        ensure_writable(args.index_file, what="index file")
    ref_paths, query_paths = list_images(args.reference), list_images(args.query)
    descriptor = create_descriptor(args.method, args)
    calibration = None
    depth = args.top_k
    spec = acceptance_from_arguments(args)
    if spec is not None:
        depth = max(args.top_k, spec.depth)
    if args.calibration:
        from fdnet.decisions.calibration import load_calibration

        calibration = load_calibration(args.calibration)
        calibration.check(descriptor, sequence_length=args.sequence_length if args.sequence_length > 1 else 0,
                          source=args.calibration)
        depth = max(args.top_k, calibration.spec.depth)  # the rule may need more candidates than are written
    rule = spec if spec is not None else (calibration.spec if calibration is not None else None)
    neighbourhood = _reference_times_and_positions(ref_paths)
    if rule is not None:  # e.g. radius_m: image folders have no positions; refused before describing
        rule.check_available({"images", *neighbourhood}, "fdnet match (references without "
                             + ("positions)" if "reference_times" in neighbourhood else "timestamps or positions)"))
    if settings is not None and not descriptor.dot_product_similarity:
        raise ConfigError(f"method {descriptor.name!r} does not compare vectors by dot product, so a "
                          "faiss index would rank by the wrong measure; use --index exact")
    if args.sequence_length > 1 and args.index != "exact":
        raise ConfigError("--sequence-length needs the full similarity matrix; use --index exact")
    if descriptor.needs_fit:
        print(f"{descriptor.name}: learning from the {len(ref_paths)} reference images (none supplied)")
        descriptor.fit(ref_paths)

    def describe(paths):
        return describe_paths(descriptor, paths, args.batch_size, progress=True,
                              workers=args.workers)

    if settings is None:
        refs = describe(ref_paths)
        queries = describe(query_paths)
        if args.sequence_length > 1:
            sim = sequence_similarity(similarity_matrix(queries, refs, descriptor.similarity), args.sequence_length)
            indices, scores = top_k_of_matrix(sim, depth)
        else:
            indices, scores = top_k(queries, refs, depth, similarity=descriptor.similarity)
    else:
        index = _cached_index(args.index_file, descriptor, ref_paths, settings) if args.index_file else None
        if index is None:
            index = VectorIndex(descriptor.dim, settings)
            for _, vectors in describe_stream(descriptor, ref_paths, args.batch_size, workers=args.workers,
                                              progress=True):
                index.add(vectors)  # the map goes into the index chunk by chunk
            t0 = time.perf_counter()
            index.build()
            built = time.perf_counter() - t0
            if args.index_file:
                index.save(args.index_file, metadata={"fingerprint": descriptor.fingerprint(),
                                                      "references": _names_digest(ref_paths),
                                                      "method": descriptor.name})
                print(f"built the {settings.kind} index of {len(ref_paths)} references ({built:.1f} s), "
                      f"saved to {args.index_file}")
        else:
            print(f"loaded the {settings.kind} index of {len(ref_paths)} references from {args.index_file}")
        queries = describe(query_paths)
        indices, scores = index.search(queries, depth)

    buffer = io.StringIO()
    writer = csv.writer(buffer)
    header = ["query_index", "query", "rank", "reference_index", "reference", "score"]
    decision = accepted = None
    if calibration is not None or spec is not None:
        from fdnet.decisions.acceptance import Candidates, decide

        candidates = Candidates(indices, scores, similarity_ceiling=float(descriptor.similarity_ceiling),
                                query_paths=query_paths, reference_paths=ref_paths, **neighbourhood)
        if calibration is not None:
            decision, accepted = calibration.decide(candidates)
            header += ["acceptance_score", "accepted"]
        else:
            decision = decide(spec, candidates)
            header += ["acceptance_score"]
    writer.writerow(header)
    for q, (row_i, row_s) in enumerate(zip(indices, scores)):
        for rank, (i, s) in enumerate(zip(row_i, row_s), start=1):
            chosen = accepted is not None and i == decision.match[q] and bool(accepted[q])
            # rows beyond --top-k only for the match the rule accepted (a re-ranking rule may pick it)
            if i >= 0 and (rank <= args.top_k or chosen):
                row = [q, spreadsheet_text(query_paths[q].name), rank, int(i), spreadsheet_text(ref_paths[i].name),
                       f"{float(s):.6f}"]
                if decision is not None:
                    row.append(f"{decision.score[q]:.6f}")
                if accepted is not None:
                    row.append(int(chosen))
                writer.writerow(row)
    atomic_write_text(args.out, buffer.getvalue())
    print(f"wrote {args.out}: top-{args.top_k} of {len(ref_paths)} references for {len(query_paths)} queries "
          f"({descriptor.name})")
    if calibration is not None:
        print(f"{int(accepted.sum())} of {len(query_paths)} queries accepted by {calibration.rule} at threshold "
              f"{calibration.threshold:.6g} (calibrated for precision {calibration.target_precision:g}); the "
              f"others are new places")
    return 0
