"""`fdnet database`: a persistent place database (one SQLite file) for loop closure and
relocalisation. See docs/database.md for the format and its guarantees."""

from __future__ import annotations

import argparse

from fdnet.cli.common import (
    acceptance_from_arguments,
    add_decision_arguments,
    add_device_argument,
    add_method_arguments,
    add_pipeline_arguments,
)
from fdnet.matching.index import INDEX_KINDS


def _positive_int(text: str) -> int:
    value = _whole_number(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    value = _whole_number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def _finite_number(text: str) -> float:
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from exc
    if value != value or value in (float("inf"), float("-inf")):  # nan would keep no row, inf all or none
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def _whole_number(text: str) -> int:
    try:
        return int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from exc


def register(sub) -> None:
    p = sub.add_parser("database", help="build, extend, query and inspect a persistent place database")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)

    build = actions.add_parser("build", help="describe a folder of images and write them as a new database file")
    build.add_argument("--images", required=True, help="folder of map images (traversal order)")
    build.add_argument("--db", required=True, help="database file to write, e.g. map.db")
    build.add_argument(
        "--overwrite", action="store_true", help="replace an existing place database at --db (in one transaction)"
    )
    add_method_arguments(build)
    build.add_argument(
        "--index",
        choices=list(INDEX_KINDS),
        default="flat",
        help="faiss index for dot-product methods: flat = exact (default); ivf (IVF-Flat), "
        "ivfpq (IVF-PQ, compressed) and hnsw are approximate, for maps of 10^5-10^6 places. "
        "Approximate indexes are built at the end of build and cached beside the file "
        "(FILE.fdnet-index, derived data: deleting it only costs a rebuild)",
    )
    build.add_argument(
        "--index-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an index setting (repeatable): ivf_lists, ivf_probe, pq_bytes, refine, train_points, "
        "hnsw_neighbors, hnsw_ef_construction, hnsw_ef_search (see docs/performance.md); "
        "compressed_from (places, default 2000000: from there the vectors are kept in FILE.vectors "
        "and searched through compressed codes, see docs/guide.md)",
    )
    add_pipeline_arguments(build)
    add_device_argument(build)
    build.set_defaults(func=run_build)

    add = actions.add_parser(
        "add",
        help="describe more images and append them to a database (one transaction)",
        description="Describe the images with the descriptor the database records and append them in one "
        "transaction. The method options are optional: give them to describe with another copy of "
        "that model (e.g. its run directory moved); its fingerprint must match the database's.",
    )
    add.add_argument("--db", required=True, help="database file")
    add.add_argument("--images", required=True, help="folder of images to append")
    add.add_argument(
        "--allow-duplicates",
        action="store_true",
        help="add images whose name is already in the database (default: skip and report them)",
    )
    add_method_arguments(add, required=False)
    add_pipeline_arguments(add)
    add_device_argument(add)
    add.set_defaults(func=run_add)

    query = actions.add_parser("query", help="rank the database's places for each query image")
    query.add_argument("--db", required=True, help="database file")
    query.add_argument("--images", required=True, help="folder of query images")
    query.add_argument("--top-k", type=_positive_int, default=5, help="candidates per query (at least 1)")
    query.add_argument(
        "--exclude-last",
        type=_non_negative_int,
        default=0,
        help="ignore the most recently added N places (a robot's own recent frames)",
    )
    query.add_argument(
        "--min-score", type=_finite_number, default=None, help="only report candidates scoring at least this"
    )
    add_decision_arguments(
        query,
        "a calibration from `fdnet calibrate` (default: the one stored in the database by "
        "`fdnet calibrate --db`, if any): adds acceptance_score and accepted columns",
    )
    query.add_argument(
        "--out", help="CSV to write (query,rank,place,place_index,score[,acceptance_score,accepted]); " "default: print"
    )
    add_pipeline_arguments(query)
    add_device_argument(query)
    query.set_defaults(func=run_query)

    info = actions.add_parser("info", help="print the database's identity and size as one JSON object")
    info.add_argument("--db", required=True, help="database file")
    info.set_defaults(func=run_info)


def _options_given(args) -> bool:
    """Whether ``add`` was given method options (else it describes with the database's own)."""
    from fdnet.cli.common import METHOD_FLAGS

    return bool(args.method or args.method_set or any(getattr(args, k, None) for k in METHOD_FLAGS))


def _print_to_stderr(message: str) -> None:
    import sys

    print(message, file=sys.stderr)


def run_build(args) -> int:
    """``database build``, in one process or in each process of a torchrun launch
    (:mod:`fdnet.descriptors.sharding`: each describes its block of the images, rank 0 writes the
    database and alone prints)."""
    from fdnet.cli.common import check_pipeline_arguments, file_options
    from fdnet.descriptors.pipeline import PipelineSettings
    from fdnet.descriptors.sharding import launch
    from fdnet.tasks.database import BuildRequest, build_database

    with launch() as shards:
        shards.collectively(lambda: check_pipeline_arguments(args))
        summary = build_database(
            BuildRequest(
                args.images,
                args.db,
                args.method,
                method_options=lambda m: file_options(args, m),
                device=args.device,
                overwrite=args.overwrite,
                index=args.index,
                index_set=tuple(args.index_set),
                pipeline=PipelineSettings(batch_size=args.batch_size, workers=args.workers, progress=True),
            )
        )
        print("\n".join(summary.lines()))
    return 0


def run_add(args) -> int:
    from fdnet.cli.common import check_pipeline_arguments, file_options
    from fdnet.descriptors.pipeline import PipelineSettings
    from fdnet.descriptors.sharding import refuse_under_torchrun
    from fdnet.tasks.database import AddRequest, add_to_database

    refuse_under_torchrun("fdnet database add")  # every process would append the images
    check_pipeline_arguments(args)
    given = _options_given(args)
    summary = add_to_database(
        AddRequest(
            args.db,
            args.images,
            method=args.method,
            method_options=(lambda m: file_options(args, m)) if given else None,
            device=args.device,
            allow_duplicates=args.allow_duplicates,
            pipeline=PipelineSettings(batch_size=args.batch_size, workers=args.workers, progress=True),
        )
    )
    print("\n".join(summary.lines()))
    return 0


def run_query(args) -> int:
    import sys

    from fdnet.cli.common import check_pipeline_arguments
    from fdnet.descriptors.pipeline import PipelineSettings
    from fdnet.tasks.database import QueryRequest, query_database

    check_pipeline_arguments(args)
    result = query_database(
        QueryRequest(
            args.db,
            args.images,
            top_k=args.top_k,
            exclude_last=args.exclude_last,
            min_score=args.min_score,
            accept=acceptance_from_arguments(args),
            calibration=args.calibration,
            out=args.out,
            device=args.device,
            pipeline=PipelineSettings(batch_size=args.batch_size, workers=args.workers, progress=True),
        ),
        log=_print_to_stderr,
    )
    if args.out:
        print("\n".join(result.lines()))
    else:
        sys.stdout.write(result.csv_text)
    return 0


def run_info(args) -> int:
    import json

    from fdnet.tasks.database import database_info

    print(json.dumps(database_info(args.db, log=_print_to_stderr), indent=2, sort_keys=True))
    return 0
