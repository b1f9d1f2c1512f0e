"""`fdnet match`: rank reference images (the map) for each query image.

Images are listed in fdnet's one order (:func:`fdnet.data.images.list_images`: natural order of
file names), and every output row carries both the indices and the file names.
"""

from __future__ import annotations

from fdnet.cli.common import add_method_arguments


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
    p.add_argument("--index", choices=["exact", "flat", "hnsw", "ivf"], default="exact",
                   help="exact blocked search (default) or a faiss index (dot-product methods only)")
    p.add_argument("--sequence-length", type=int, default=0,
                   help="SeqSLAM sequence matching over this many consecutive queries (0 = single image)")
    p.add_argument("--out", required=True,
                   help="CSV to write: query_index,query,rank,reference_index,reference,score (indices are "
                        "positions in natural file-name order, names the image file names)")
    p.add_argument("--batch-size", type=int, default=64)
    p.set_defaults(func=run)


def run(args) -> int:
    import csv
    import io

    from fdnet.cli.common import create_descriptor
    from fdnet.data.images import list_images
    from fdnet.descriptors.base import describe_paths
    from fdnet.errors import ConfigError
    from fdnet.io import atomic_write_text, ensure_writable
    from fdnet.matching.index import IndexSettings, VectorIndex
    from fdnet.matching.sequence import sequence_similarity
    from fdnet.matching.similarity import similarity_matrix, top_k, top_k_of_matrix

    if args.top_k < 1:
        raise ConfigError("--top-k must be at least 1")
    ensure_writable(args.out, what="matches CSV")  # before describing every image, not after
    ref_paths, query_paths = list_images(args.reference), list_images(args.query)
    descriptor = create_descriptor(args.method, args)
    if descriptor.needs_fit:
        print(f"{descriptor.name}: learning from the {len(ref_paths)} reference images (none supplied)")
        descriptor.fit(ref_paths)
    refs = describe_paths(descriptor, ref_paths, args.batch_size, progress=True)
    queries = describe_paths(descriptor, query_paths, args.batch_size, progress=True)

    if args.sequence_length > 1:
        if args.index != "exact":
            raise ConfigError("--sequence-length needs the full similarity matrix; use --index exact")
        sim = sequence_similarity(similarity_matrix(queries, refs, descriptor.similarity), args.sequence_length)
        indices, scores = top_k_of_matrix(sim, args.top_k)
    elif args.index == "exact":
        indices, scores = top_k(queries, refs, args.top_k, similarity=descriptor.similarity)
    else:
        if not descriptor.dot_product_similarity:
            raise ConfigError(f"method {descriptor.name!r} does not compare vectors by dot product, so a "
                              "faiss index would rank by the wrong measure; use --index exact")
        index = VectorIndex(descriptor.dim, IndexSettings(kind=args.index))
        index.add(refs)
        indices, scores = index.search(queries, args.top_k)

    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["query_index", "query", "rank", "reference_index", "reference", "score"])
    for q, (row_i, row_s) in enumerate(zip(indices, scores)):
        for rank, (i, s) in enumerate(zip(row_i, row_s), start=1):
            if i >= 0:
                writer.writerow([q, query_paths[q].name, rank, int(i), ref_paths[i].name, f"{float(s):.6f}"])
    atomic_write_text(args.out, buffer.getvalue())
    print(f"wrote {args.out}: top-{args.top_k} of {len(ref_paths)} references for {len(query_paths)} queries "
          f"({descriptor.name})")
    return 0
