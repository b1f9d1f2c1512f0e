"""`fdnet groundtruth`: write the explicit ground-truth CSV (``query_index,reference_indices``) that
every command accepts, for a user's own route or for a dataset folder.

Three sources:

* ``--positions REFERENCE.csv QUERY.csv --tolerance-m 25``: one row per image in traversal order,
  a header naming an image column and ``lat,lon`` (degrees) or ``easting,northing`` (metres);
  output rows are the query file's rows;
* ``--aligned --tolerance-frames N`` with ``--num-queries/--num-references`` or two image folders
  ``--reference DIR --query DIR``: frame i of the query is frame i of the reference;
* ``--dataset ROOT [--dataset-format NAME] [--split test]``: a dataset adapter's ground truth.

Prints a summary (queries with at least one true match, mean matches per query) and warns when
more than ``--warn-unmatched`` of the queries have none.
"""

from __future__ import annotations

import argparse
import sys


def register(sub) -> None:
    p = sub.add_parser(
        "groundtruth",
        help="build a ground-truth CSV from GPS positions, frame alignment or a dataset folder",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--positions", nargs=2, metavar=("REFERENCE_CSV", "QUERY_CSV"),
                        help="position files of the reference and the query traverse")
    source.add_argument("--aligned", action="store_true",
                        help="frame-aligned traverses: query frame i is reference frame i")
    source.add_argument("--dataset", metavar="ROOT", help="a dataset folder read by a dataset adapter")
    p.add_argument("--tolerance-m", type=float, default=None,
                   help="--positions: references within this many metres count as correct (default 25)")
    p.add_argument("--image-column", default=None, help="--positions: name of the image column")
    p.add_argument("--tolerance-frames", type=int, default=None,
                   help="--aligned: references within this many frames count as correct (default 0)")
    p.add_argument("--num-queries", type=int, default=None, help="--aligned: number of query images")
    p.add_argument("--num-references", type=int, default=None, help="--aligned: number of reference images")
    p.add_argument("--reference", default=None,
                   help="--aligned: reference image folder; --dataset: reference condition")
    p.add_argument("--query", default=None, help="--aligned: query image folder; --dataset: query condition")
    p.add_argument("--dataset-format", default=None,
                   help="--dataset: layout name (default: detected): nordland, alderley, oxford_robotcar, "
                        "st_lucia, fas, vprbench, vpr_tutorial, vg_benchmark, folders")
    p.add_argument("--split", default=None, help="--dataset: named split (train/test/all) or START:END")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="--dataset: a protocol setting of the format, e.g. tolerance=3 (repeatable)")
    p.add_argument("--out", required=True, help="ground-truth CSV to write")
    p.add_argument("--warn-unmatched", type=float, default=0.2, metavar="FRACTION",
                   help="warn when more than this fraction of queries has no true match (default 0.2)")
    p.set_defaults(func=run)


def _from_positions(args):
    from fdnet.data.formats.positions import positions_ground_truth, read_positions

    ref_csv, query_csv = args.positions
    reference = read_positions(ref_csv, image_column=args.image_column)
    query = read_positions(query_csv, image_column=args.image_column)
    tolerance = 25.0 if args.tolerance_m is None else args.tolerance_m
    return positions_ground_truth(reference, query, tolerance)


def _from_alignment(args):
    from fdnet.data.formats._common import image_files
    from fdnet.data.groundtruth import GroundTruth
    from fdnet.errors import ConfigError

    tolerance = 0 if args.tolerance_frames is None else args.tolerance_frames
    if args.reference or args.query:
        if not (args.reference and args.query):
            raise ConfigError("--aligned with folders needs both --reference DIR and --query DIR")
        if args.num_queries is not None or args.num_references is not None:
            raise ConfigError("give either --reference/--query folders or --num-queries/--num-references, not both")
        num_references = len(image_files(args.reference))
        num_queries = len(image_files(args.query))
    else:
        if args.num_queries is None or args.num_references is None:
            raise ConfigError("--aligned needs --num-queries and --num-references (or --reference DIR --query DIR)")
        num_queries, num_references = args.num_queries, args.num_references
    if num_queries <= 0 or num_references <= 0:
        raise ConfigError(f"--num-queries and --num-references must be positive, got {num_queries}, {num_references}")
    return GroundTruth.aligned(num_queries, num_references, tolerance)


def _from_dataset(args):
    from fdnet.config import parse_overrides
    from fdnet.data.formats import open_split

    split = open_split(args.dataset, reference=args.reference, query=args.query,
                       dataset_format=args.dataset_format, split=args.split, check_sizes=False,
                       **parse_overrides(args.set))
    print(f"{split.description}: {len(split.query)} queries ({split.query.name}), "
          f"{len(split.reference)} references ({split.reference.name})")
    return split.ground_truth


def run(args) -> int:
    from fdnet.errors import ConfigError

    if args.positions:
        if args.tolerance_frames is not None:
            raise ConfigError("--tolerance-frames is for --aligned; with --positions use --tolerance-m")
        gt = _from_positions(args)
    elif args.aligned:
        if args.tolerance_m is not None:
            raise ConfigError("--tolerance-m is for --positions; with --aligned use --tolerance-frames")
        gt = _from_alignment(args)
    else:
        gt = _from_dataset(args)
    gt.to_csv(args.out)
    summary = gt.summary()
    n = summary["num_queries"]
    with_match = summary["queries_with_match"]
    print(f"wrote {args.out}: {n} queries x {summary['num_references']} references ({gt.description})")
    print(f"queries with at least one true match: {with_match}/{n} ({100.0 * with_match / max(n, 1):.1f} %)")
    print(f"mean true matches per query: {summary['mean_matches_per_query']:.2f}")
    unmatched = n - with_match
    if n and unmatched / n > args.warn_unmatched:
        print(f"warning: {unmatched} of {n} queries ({100.0 * unmatched / n:.1f} %) have no true match; "
              f"check the tolerance, the units (degrees vs metres) and that both traverses cover the "
              f"same route", file=sys.stderr)
    return 0
