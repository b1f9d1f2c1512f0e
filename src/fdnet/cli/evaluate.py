"""`fdnet evaluate`: score methods (or a precomputed similarity matrix) against ground truth.

Two input modes:

* methods on images: ``--data DIR --reference COND --query COND --method NAME[,NAME...]``; DIR
  has one sub-folder per condition, ground truth is frame alignment within ``--tolerance`` frames,
  or the explicit list of ``--ground-truth CSV`` (``query_index,reference_indices``, indices over
  all images of the two folders in natural order, :func:`fdnet.data.images.list_images`);
  with ``--dataset-format NAME`` the adapter's split and protocol, and ``--ground-truth`` then
  replaces the adapter's ground truth for the chosen split (indices over the split's images);
* a precomputed matrix: ``--similarity FILE.npy --ground-truth FILE.csv`` (or the frame-aligned
  ground truth of ``--data/--reference/--query``, which also lets ``--plots`` show images).

A ground-truth CSV that names its images (``fdnet groundtruth`` writes ``query_name`` and
``reference_names``) is checked against the images evaluated: a different order or other files
stop the command with the first mismatching row. Output paths are checked before any work.

Prints a table (protocol named in its header); ``--json`` writes the numbers (one object per
method, ``{"results": [...]}`` for several); ``--plots DIR`` writes the PR curves, similarity
matrices and example matches as PNG.

``--accept RULE[,RULE...]`` names the acceptance rules whose scores the PR numbers threshold
(:mod:`fdnet.decisions.acceptance`; one table row per method and rule; the JSON's top-level
numbers are the first rule's, named by ``acceptance``, and ``per_acceptance`` holds every rule's
when there are several). Default: ``margin`` (chosen on validation pairs, docs/decisions.md);
under ``--protocol vprbench`` ``raw``, VPR-Bench's own definition.
"""

from __future__ import annotations

from fdnet.cli.common import add_device_argument, add_method_arguments, dataset_format_list


def register(sub) -> None:
    p = sub.add_parser(
        "evaluate",
        help="evaluate methods or a similarity matrix: R@N, R@100P, P@maxR, AUC-PR, timings",
        description="Evaluate place-recognition methods on a reference/query split (or a precomputed "
        "query x reference similarity matrix) under a named protocol.",
    )
    _add_data_arguments(p)
    _add_methods_arguments(p)
    _add_similarity_arguments(p)
    _add_output_arguments(p)
    p.add_argument(
        "--allow-training-frames",
        action="store_true",
        help="evaluate a trained method on frames it was trained on (refused by default: the numbers "
        "would measure memory, not recognition)",
    )
    p.set_defaults(func=run)


def _add_data_arguments(p) -> None:
    """The dataset: its conditions, frames, format and ground truth."""
    data = p.add_argument_group("data")
    data.add_argument("--data", help="dataset folder with one sub-folder per condition")
    data.add_argument("--reference", help="condition (sub-folder of --data) used as the map")
    data.add_argument("--query", help="condition (sub-folder of --data) used as queries")
    data.add_argument(
        "--tolerance",
        type=int,
        default=None,
        help="frame-aligned ground truth: query frame i matches reference frames i +- N (default 0; "
        "with --dataset-format, the format's paper tolerance)",
    )
    data.add_argument(
        "--filter-frames",
        action="store_true",
        help="frame-aligned folders: drop dark (tunnel) and near-duplicate (stationary) frames from "
        "both conditions after --frames, as the paper does (fdnet.data.filters defaults, "
        "kept frames cached under $FDNET_CACHE/filters); with --dataset-format nordland: "
        "its filter_frames setting",
    )
    data.add_argument(
        "--dataset-format",
        metavar="NAME",
        help=f"read --data in a published layout ({dataset_format_list()}) with the "
        "paper's protocol; see docs/datasets.md",
    )
    data.add_argument("--split", help="with --dataset-format: a named split (train/test/all) or START:END")
    data.add_argument(
        "--format-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="with --dataset-format: a protocol setting of the format, e.g. tolerance_m=25",
    )
    data.add_argument("--frames", metavar="START:END", help="evaluate only these frames (END exclusive)")
    data.add_argument(
        "--ground-truth",
        metavar="CSV",
        help="explicit ground truth 'query_index,reference_indices' (space-separated "
        "list; indices in natural file-name order) instead of frame alignment; with "
        "--dataset-format it replaces the format's ground truth for the chosen split. "
        "Names in the CSV (fdnet groundtruth writes them) must match the images",
    )


def _add_methods_arguments(p) -> None:
    """The methods to evaluate and how images are described."""
    from fdnet.cli.common import thread_count

    methods = p.add_argument_group("methods")
    add_method_arguments(methods, multiple=True, required=False)
    methods.add_argument("--batch-size", type=int, default=64, help="images described per batch (default 64)")
    methods.add_argument(
        "--workers",
        type=int,
        default=None,
        help="image decoding processes running alongside the model (default: one per spare "
        "core, at least 1; 0 = decode in the main process)",
    )
    add_device_argument(methods)
    methods.add_argument(
        "--sequence-length",
        type=int,
        default=1,
        help="rank by SeqSLAM sequence similarity over this many consecutive queries " "(1 = single images)",
    )
    methods.add_argument("--threads", type=thread_count(), help="torch CPU threads (default: all cores)")


def _add_similarity_arguments(p) -> None:
    """A similarity matrix computed elsewhere, evaluated instead of methods."""
    matrix = p.add_argument_group("precomputed similarity")
    matrix.add_argument(
        "--similarity", metavar="FILE.npy", help="a (queries x references) score matrix, higher = more similar"
    )
    matrix.add_argument(
        "--distance", action="store_true", help="the --similarity file holds distances (lower = more similar)"
    )
    matrix.add_argument("--name", help="method name reported for --similarity (default: file name)")


def _add_output_arguments(p) -> None:
    """The metrics' protocol, decisions, and what is written."""
    out = p.add_argument_group("metrics and output")
    out.add_argument(
        "--protocol",
        choices=["recall-over-queries", "vprbench"],
        default="recall-over-queries",
        help="PR definition: recall over queries with a true match (paper, VPR_Tutorial) or "
        "VPR-Bench's (recall over correct top-1 matches, sklearn AUC); default recall-over-queries",
    )
    out.add_argument(
        "--thresholds",
        type=int,
        help="recall-over-queries: sweep N uniform thresholds over min-max-normalised "
        "scores (the paper uses 500) instead of every distinct score",
    )
    out.add_argument(
        "--accept",
        metavar="RULE[,RULE...]",
        help="acceptance rules whose scores the PR curve thresholds (R@100P, R@99P, R@95P, P@maxR, "
        "AUC-PR per rule): raw (best-match similarity), margin (best minus the best outside a "
        "neighbourhood of the best), ratio (Lowe's ratio), verified (inlier count of local "
        "features matched to the top-K candidates; images of at least 80 px), or SCORE+GATE "
        "(e.g. margin+floor, margin+verified); "
        "default margin, raw under --protocol vprbench. Recall@N does not depend on it",
    )
    out.add_argument(
        "--accept-set",
        action="append",
        default=[],
        metavar="[RULE:]KEY=VALUE",
        help="an acceptance rule setting (repeatable), e.g. radius=3 (neighbourhood in frames), "
        "ratio:ceiling=1, floor:min=0.5; docs/decisions.md lists them",
    )
    out.add_argument("--json", metavar="FILE", help="write the results as JSON")
    out.add_argument("--no-curve", action="store_true", help="with --json: leave the PR curve points out of the JSON")
    out.add_argument(
        "--predictions",
        type=int,
        default=0,
        metavar="K",
        help="with --json: add each query's K best references (indices, names, scores, correct) to " "the JSON",
    )
    out.add_argument(
        "--table",
        choices=("csv", "markdown", "latex"),
        help="also print a method x data table (R@1, R@100P, AUC-PR) in this format",
    )
    out.add_argument("--plots", metavar="DIR", help="write PR curves, similarity matrices and example matches")
    out.add_argument(
        "--examples",
        type=int,
        default=None,
        help="with --plots: queries shown in the example-matches figure (default 6)",
    )


def run(args) -> int:
    from fdnet.cli.common import method_options
    from fdnet.tasks.evaluate import EvaluateSettings, evaluate_command

    settings = EvaluateSettings(
        method=args.method,
        method_options=lambda name: method_options(args, name),
        similarity=args.similarity,
        distance=args.distance,
        name=args.name,
        data=args.data,
        reference=args.reference,
        query=args.query,
        tolerance=args.tolerance,
        filter_frames=args.filter_frames,
        dataset_format=args.dataset_format,
        split=args.split,
        format_set=args.format_set,
        frames=args.frames,
        ground_truth=args.ground_truth,
        batch_size=args.batch_size,
        workers=args.workers,
        device=args.device,
        sequence_length=args.sequence_length,
        threads=args.threads,
        protocol=args.protocol,
        thresholds=args.thresholds,
        accept=args.accept,
        accept_set=args.accept_set,
        json=args.json,
        include_curve=not args.no_curve,
        plots=args.plots,
        predictions=args.predictions,
        table=args.table,
        command=getattr(args, "command_line", None),
        examples=args.examples,
        allow_training_frames=args.allow_training_frames,
    )
    evaluate_command(settings, show=print)
    return 0
