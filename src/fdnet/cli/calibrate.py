"""`fdnet calibrate`: choose an acceptance threshold that reaches a target precision on a
validation pair, and store it for `fdnet match` and `fdnet database query`.

Runs the method on the pair (the same split options as `fdnet evaluate`), scores every query with
the acceptance rule (``--accept``, ``--accept-set``; on sequence scores with
``--sequence-length``), and keeps the threshold with the largest recall whose precision reaches
``--target-precision`` (:func:`fdnet.tasks.calibrate.calibrate`). The result (rule,
settings, threshold, target, precision and recall reached, what it was measured on, method and
descriptor fingerprint) goes to ``--out FILE.yaml``, to ``calibration.yaml`` in the run directory
of ``--checkpoint`` (``--store-in-run``) and/or into a place database (``--db``); at least one.
"""

from __future__ import annotations

from fdnet.cli.common import add_device_argument, add_method_arguments, add_pipeline_arguments


def register(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help="choose the acceptance threshold that reaches a target precision on a validation pair",
        description="Score a validation pair with an acceptance rule and store the threshold that reaches "
        "--target-precision (with the model's fingerprint), for `fdnet match --calibration` and "
        "`fdnet database query`.",
    )
    data = p.add_argument_group("validation pair (as for fdnet evaluate)")
    data.add_argument("--data", required=True, help="dataset folder with one sub-folder per condition")
    data.add_argument("--reference", help="condition used as the map")
    data.add_argument("--query", help="condition used as queries")
    data.add_argument(
        "--tolerance",
        type=int,
        default=None,
        help="frame-aligned ground truth: query frame i matches reference frames i +- N (default 0)",
    )
    data.add_argument("--frames", metavar="START:END", help="calibrate on these frames only (END exclusive)")
    data.add_argument("--filter-frames", action="store_true", help="drop dark and near-duplicate frames first")
    data.add_argument("--dataset-format", metavar="NAME", help="read --data in a published layout (see evaluate)")
    data.add_argument("--split", help="with --dataset-format: a named split or START:END")
    data.add_argument(
        "--format-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="with --dataset-format: a protocol setting of the format",
    )
    data.add_argument("--ground-truth", metavar="CSV", help="explicit ground truth instead of frame alignment")
    methods = p.add_argument_group("method")
    add_method_arguments(methods)
    add_pipeline_arguments(methods)
    add_device_argument(methods)
    methods.add_argument(
        "--sequence-length",
        type=int,
        default=1,
        help="calibrate SeqSLAM sequence scores over this many consecutive queries (1 = single "
        "images); the calibration is then only valid with the same --sequence-length",
    )
    decision = p.add_argument_group("decision")
    decision.add_argument(
        "--accept",
        default=None,
        metavar="RULE",
        help="the acceptance rule (one expression, e.g. margin, ratio, margin+floor; default " "margin)",
    )
    decision.add_argument(
        "--accept-set",
        action="append",
        default=[],
        metavar="[RULE:]KEY=VALUE",
        help="a setting of the rule (repeatable), e.g. radius=3",
    )
    decision.add_argument(
        "--choose",
        action="append",
        default=[],
        metavar="KEY=V1,V2,...",
        help="also choose a rule setting on this pair (repeatable), e.g. radius=0,1,2,3,5: every "
        "value is tried and the one reaching the target with the largest recall is stored",
    )
    decision.add_argument(
        "--target-precision",
        type=float,
        default=1.0,
        help="precision the threshold must reach on the pair, in (0, 1] (default 1.0)",
    )
    out = p.add_argument_group("where to store it (at least one)")
    out.add_argument("--out", metavar="FILE.yaml", help="write the calibration as YAML")
    out.add_argument(
        "--store-in-run", action="store_true", help="write calibration.yaml into the --checkpoint run directory"
    )
    out.add_argument(
        "--db",
        metavar="MAP.db",
        help="store it in this place database (built with the same model); `fdnet database query` " "then uses it",
    )
    p.add_argument(
        "--allow-training-frames",
        action="store_true",
        help="calibrate a trained method on frames it was trained on (refused by default: its scores "
        "there are not those of new places)",
    )
    p.set_defaults(func=run)


def run(args) -> int:
    from fdnet.cli.common import check_pipeline_arguments, create_descriptor, method_options
    from fdnet.descriptors.pipeline import PipelineSettings
    from fdnet.errors import ConfigError
    from fdnet.evaluation.splits import SplitSpec
    from fdnet.tasks.calibrate import CalibrateRequest, calibrate_command

    check_pipeline_arguments(args)
    options = method_options(args, args.method)  # once: the descriptor and the run it is stored in
    request = CalibrateRequest(
        split=SplitSpec(
            args.data,
            args.reference,
            args.query,
            dataset_format=args.dataset_format,
            split=args.split,
            format_set=tuple(args.format_set),
            frames=args.frames,
            tolerance=args.tolerance,
            filter_frames=args.filter_frames,
            ground_truth=args.ground_truth,
        ),
        target_precision=args.target_precision,
        accept=args.accept,
        accept_set=tuple(args.accept_set),
        choose=tuple(args.choose),
        sequence_length=args.sequence_length,
        out=args.out,
        store_in_run=args.store_in_run,
        run_dir=options.get("checkpoint") if args.store_in_run else None,
        db=args.db,
        allow_training_frames=args.allow_training_frames,
        pipeline=PipelineSettings(args.batch_size, args.workers, progress=True),
    )
    result = calibrate_command(request, lambda: create_descriptor(args.method, args, options))
    calibration = result.calibration
    print(
        f"{calibration.method}, rule {calibration.rule}: threshold {calibration.threshold:.6g} reaches precision "
        f"{calibration.precision:.3f} at recall {calibration.recall:.3f} ({calibration.accepted} of "
        f"{calibration.num_queries} queries accepted; target {calibration.target_precision:g})"
    )
    for note in calibration.notes:
        print(f"note: {note}")
    for where in result.written:
        print(f"wrote {where}")
    if result.failed:
        if not result.written:  # nothing kept it: the calibration goes to stdout instead
            import yaml

            print("# the calibration, written nowhere (save it as a .yaml file):")
            print(yaml.safe_dump(calibration.to_dict(), sort_keys=False), end="")
        raise ConfigError("; ".join(result.failed))
    return 0
