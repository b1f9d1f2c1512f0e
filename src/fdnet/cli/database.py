"""`fdnet database`: a persistent place database for loop closure / relocalisation."""

from __future__ import annotations

from fdnet.cli.common import add_method_arguments


def register(sub) -> None:
    p = sub.add_parser("database", help="build, extend and query a persistent place database")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)

    build = actions.add_parser("build", help="describe a folder of images and save them as a database")
    build.add_argument("--images", required=True, help="folder of map images (traversal order)")
    build.add_argument("--out", required=True, help="database folder to write")
    add_method_arguments(build)
    build.add_argument("--index", choices=["flat", "hnsw", "ivf"], default="flat",
                       help="faiss index for dot-product methods (flat = exact)")
    build.set_defaults(func=run_build)

    add = actions.add_parser("add", help="describe more images and append them to a database")
    add.add_argument("--db", required=True, help="database folder")
    add.add_argument("--images", required=True, help="folder of images to append")
    add.set_defaults(func=run_add)

    query = actions.add_parser("query", help="rank the database's places for each query image")
    query.add_argument("--db", required=True, help="database folder")
    query.add_argument("--images", required=True, help="folder of query images")
    query.add_argument("--top-k", type=int, default=5)
    query.add_argument("--exclude-last", type=int, default=0,
                       help="ignore the most recently added N places (a robot's own recent frames)")
    query.add_argument("--min-score", type=float, default=None, help="only report candidates scoring at least this")
    query.add_argument("--out", help="CSV to write (query,rank,place,place_index,score); default: print")
    query.set_defaults(func=run_query)


def _describe(descriptor, folder):
    from fdnet.data.images import list_images
    from fdnet.descriptors.base import describe_paths

    paths = list_images(folder)
    return paths, describe_paths(descriptor, paths, progress=True)


def _open(db_folder):
    from fdnet.descriptors import create
    from fdnet.matching.database import PlaceDatabase

    meta_db = PlaceDatabase.load(db_folder)
    descriptor = create(meta_db.method, **meta_db.method_options)
    return PlaceDatabase.load(db_folder, descriptor=descriptor), descriptor


def run_build(args) -> int:
    from fdnet.cli.common import create_descriptor, method_options
    from fdnet.errors import ConfigError
    from fdnet.matching.database import PlaceDatabase
    from fdnet.matching.index import IndexSettings

    descriptor = create_descriptor(args.method, args)
    if descriptor.needs_fit:
        raise ConfigError(f"method {descriptor.name!r} must be given what it learns from (e.g. --vocabulary) "
                          "to build a database that later queries can reuse")
    paths, vectors = _describe(descriptor, args.images)
    from pathlib import Path

    from fdnet.cli.common import FILE_OPTIONS

    options = method_options(args, args.method)
    # Absolute paths: later `add`/`query` calls may run from another directory.
    options.update({k: str(Path(v).resolve()) for k, v in options.items() if k in FILE_OPTIONS})
    db = PlaceDatabase.for_descriptor(descriptor, IndexSettings(kind=args.index), method_options=options)
    db.add(vectors, [str(p) for p in paths])
    db.save(args.out)
    print(f"wrote {args.out}: {len(db)} places, {descriptor.name} ({descriptor.dim}-d)")
    return 0


def run_add(args) -> int:
    db, descriptor = _open(args.db)
    paths, vectors = _describe(descriptor, args.images)
    db.add(vectors, [str(p) for p in paths])
    db.save(args.db)
    print(f"{args.db}: added {len(paths)} places, {len(db)} in all")
    return 0


def run_query(args) -> int:
    import csv
    import io
    import sys

    from fdnet.io import atomic_write_text

    db, descriptor = _open(args.db)
    paths, vectors = _describe(descriptor, args.images)
    results = db.query(vectors, k=args.top_k, exclude_last=args.exclude_last)
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["query", "rank", "place", "place_index", "score"])
    for path, matches in zip(paths, results):
        for rank, m in enumerate(matches, start=1):
            if args.min_score is None or m.score >= args.min_score:
                writer.writerow([path.name, rank, m.name, m.index, f"{m.score:.6f}"])
    if args.out:
        atomic_write_text(args.out, buffer.getvalue())
        print(f"wrote {args.out}: {len(paths)} queries against {len(db)} places")
    else:
        sys.stdout.write(buffer.getvalue())
    return 0
