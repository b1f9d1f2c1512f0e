"""`fdnet groundtruth`: write the explicit ground-truth CSV that every command accepts, for a user's
own route or for a dataset folder: ``query_index,reference_indices`` plus, when the images are
known, ``query_name,reference_names`` (so ``fdnet evaluate`` can check the indices still mean
those images). Indices are positions in natural file-name order (``frame_2`` before
``frame_10``), the order every fdnet command lists images in.

Three sources:

* ``--positions REFERENCE.csv QUERY.csv --tolerance-m 25``: a header naming ``lat,lon`` (degrees)
  or ``easting,northing`` (metres) and optionally an image column. With ``--reference DIR
  --query DIR`` rows are matched to the folders' images (by the image column, or one row per
  image in order); without folders, rows with an image column are put in natural order of the
  image names, and rows without one are taken to be the images in that order;
* ``--aligned --tolerance N`` with ``--num-queries/--num-references`` or two image folders
  ``--reference DIR --query DIR``: frame i of the query is frame i of the reference;
* ``--data ROOT [--dataset-format NAME] [--split test] [--format-set KEY=VALUE]``: a dataset adapter's ground truth,
  indices over the split's images.

Prints a summary (queries with at least one true match, mean matches per query) and warns when
more than ``--warn-unmatched`` of the queries have none. ``--out`` is checked before any work.
"""

from __future__ import annotations

import argparse
import sys

from fdnet.cli.common import dataset_format_list


def register(sub) -> None:
    p = sub.add_parser(
        "groundtruth",
        help="build a ground-truth CSV from GPS positions, frame alignment or a dataset folder",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--positions",
        nargs=2,
        metavar=("REFERENCE_CSV", "QUERY_CSV"),
        help="position files of the reference and the query traverse, or ROS bags (their image "
        "frames, positions interpolated from a NavSatFix/Odometry topic; docs/sources.md)",
    )
    source.add_argument(
        "--aligned", action="store_true", help="frame-aligned traverses: query frame i is reference frame i"
    )
    source.add_argument("--data", metavar="ROOT", help="a dataset folder read by a dataset adapter")
    p.add_argument(
        "--tolerance-m",
        type=float,
        default=None,
        help="--positions: references within this many metres count as correct (default 25)",
    )
    p.add_argument("--image-column", default=None, help="--positions: name of the image column")
    p.add_argument(
        "--tolerance",
        type=int,
        default=None,
        help="--aligned: references within this many frames count as correct (default 0)",
    )
    p.add_argument("--num-queries", type=int, default=None, help="--aligned: number of query images")
    p.add_argument("--num-references", type=int, default=None, help="--aligned: number of reference images")
    p.add_argument(
        "--reference", default=None, help="--aligned, --positions: reference image folder; --data: reference condition"
    )
    p.add_argument("--query", default=None, help="--aligned, --positions: query image folder; --data: query condition")
    p.add_argument(
        "--dataset-format",
        default=None,
        help=f"--data: layout name (default: detected): {dataset_format_list(auto=False)}",
    )
    p.add_argument("--split", default=None, help="--data: named split (train/test/all) or START:END")
    p.add_argument(
        "--format-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="--data: a protocol setting of the format, e.g. tolerance=3 (repeatable)",
    )
    p.add_argument("--out", required=True, help="ground-truth CSV to write")
    p.add_argument(
        "--warn-unmatched",
        type=float,
        default=0.2,
        metavar="FRACTION",
        help="warn when more than this fraction of queries has no true match (default 0.2)",
    )
    p.set_defaults(func=run)


def _positions_in_image_order(table, folder):
    """(table with one row per image in natural file-name order, the images' file names or None).

    With a folder, rows are matched to its images (by the image column, or one row per image in
    order). Without one, rows that name their image are sorted into the order the folder will be
    listed in; rows that do not are taken to be in that order already (no names to write)."""
    from pathlib import Path

    import numpy as np

    from fdnet.data.formats.positions import PositionTable, align_to_images
    from fdnet.data.images import list_images, natural_key
    from fdnet.errors import DataError

    if folder is not None:
        paths = list_images(folder)
        rows = align_to_images(table, paths, Path(folder))
        names = [p.name for p in paths]
    elif table.images is not None:
        names = [Path(name).name for name in table.images]
        seen: dict[str, int] = {}
        for k, name in enumerate(names):
            if name in seen:
                raise DataError(
                    f"{table.path}, line {table.lines[k]}: image {name} is listed twice "
                    f"(first on line {table.lines[seen[name]]})"
                )
            seen[name] = k
        rows = np.asarray(sorted(range(len(names)), key=lambda k: natural_key(names[k])), dtype=np.int64)
        names = [names[k] for k in rows]
    else:
        return table, None
    ordered = PositionTable(
        table.path, table.kind, table.values[rows], None if table.images is None else [table.images[k] for k in rows]
    )
    return ordered, names


def _from_positions(args):
    from fdnet.data.formats.positions import positions_ground_truth, read_positions, source_positions
    from fdnet.errors import ConfigError

    if bool(args.reference) != bool(args.query):
        raise ConfigError("--positions with image folders needs both --reference DIR and --query DIR")
    ref_csv, query_csv = args.positions

    def read(path):
        from fdnet.data import sources

        if sources.is_source(path):  # a bag: its frames with positions interpolated from its GPS/odometry
            if args.reference or args.query:
                raise ConfigError(
                    f"--positions {path}: a bag's positions are its own frames'; "
                    "--reference/--query folders are for position CSVs"
                )
            return source_positions(path)
        return read_positions(path, image_column=args.image_column)

    reference, ref_names = _positions_in_image_order(read(ref_csv), args.reference)
    query, query_names = _positions_in_image_order(read(query_csv), args.query)
    if (ref_names is None) != (query_names is None):
        without = ref_csv if ref_names is None else query_csv
        raise ConfigError(
            f"{without}: has no image column but the other position file has one; give both "
            f"an image column, or give the image folders with --reference DIR --query DIR"
        )
    tolerance = 25.0 if args.tolerance_m is None else args.tolerance_m
    return positions_ground_truth(reference, query, tolerance), query_names, ref_names


def _from_alignment(args):
    from fdnet.data.groundtruth import GroundTruth
    from fdnet.data.images import list_images
    from fdnet.errors import ConfigError

    tolerance = 0 if args.tolerance is None else args.tolerance
    query_names = reference_names = None
    if args.reference or args.query:
        if not (args.reference and args.query):
            raise ConfigError("--aligned with folders needs both --reference DIR and --query DIR")
        if args.num_queries is not None or args.num_references is not None:
            raise ConfigError("give either --reference/--query folders or --num-queries/--num-references, not both")
        reference_names = [p.name for p in list_images(args.reference)]
        query_names = [p.name for p in list_images(args.query)]
        num_references, num_queries = len(reference_names), len(query_names)
    else:
        if args.num_queries is None or args.num_references is None:
            raise ConfigError("--aligned needs --num-queries and --num-references (or --reference DIR --query DIR)")
        num_queries, num_references = args.num_queries, args.num_references
    if num_queries <= 0 or num_references <= 0:
        raise ConfigError(f"--num-queries and --num-references must be positive, got {num_queries}, {num_references}")
    return GroundTruth.aligned(num_queries, num_references, tolerance), query_names, reference_names


def _from_dataset(args):
    from fdnet.config import parse_overrides
    from fdnet.data.formats import open_split
    from fdnet.errors import ConfigError

    overrides = parse_overrides(args.format_set)
    # --tolerance / --tolerance-m are the format's protocol settings here: given, they are used (not
    # silently dropped); --format-set tolerance=... says the same
    for flag, key, value in (
        ("--tolerance", "tolerance", args.tolerance),
        ("--tolerance-m", "tolerance_m", args.tolerance_m),
    ):
        if value is not None:
            if key in overrides and overrides[key] != value:
                raise ConfigError(f"{flag} {value} and --format-set {key}={overrides[key]} disagree; give one")
            overrides[key] = value
    split = open_split(
        args.data,
        reference=args.reference,
        query=args.query,
        dataset_format=args.dataset_format,
        split=args.split,
        check_sizes=False,
        **overrides,
    )
    print(
        f"{split.description}: {len(split.query)} queries ({split.query.name}), "
        f"{len(split.reference)} references ({split.reference.name})"
    )
    return (split.ground_truth, [p.name for p in split.query.paths], [p.name for p in split.reference.paths])


def run(args) -> int:
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable

    ensure_writable(args.out, what="ground-truth CSV")
    if args.positions:
        if args.tolerance is not None:
            raise ConfigError("--tolerance is for --aligned; with --positions use --tolerance-m")
        gt, query_names, reference_names = _from_positions(args)
    elif args.aligned:
        if args.tolerance_m is not None:
            raise ConfigError("--tolerance-m is for --positions; with --aligned use --tolerance")
        gt, query_names, reference_names = _from_alignment(args)
    else:
        gt, query_names, reference_names = _from_dataset(args)
    gt.to_csv(args.out, query_names, reference_names)
    if query_names is None:
        print(
            "note: no image names to write (no image column and no image folders), so readers cannot "
            "check that the indices mean the images they evaluate",
            file=sys.stderr,
        )
    summary = gt.summary()
    n = summary["num_queries"]
    with_match = summary["queries_with_match"]
    print(f"wrote {args.out}: {n} queries x {summary['num_references']} references ({gt.description})")
    print(f"queries with at least one true match: {with_match}/{n} ({100.0 * with_match / max(n, 1):.1f} %)")
    print(f"mean true matches per query: {summary['mean_matches_per_query']:.2f}")
    unmatched = n - with_match
    if n and unmatched / n > args.warn_unmatched:
        print(
            f"warning: {unmatched} of {n} queries ({100.0 * unmatched / n:.1f} %) have no true match; "
            f"check the tolerance, the units (degrees vs metres) and that both traverses cover the "
            f"same route",
            file=sys.stderr,
        )
    return 0
