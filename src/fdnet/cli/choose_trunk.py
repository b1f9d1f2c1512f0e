"""`fdnet choose-trunk`: the trunk's backbone and block chosen on a validation pair."""

from __future__ import annotations


def register(sub) -> None:
    from fdnet.cli.common import thread_count
    from fdnet.methods.fdnet.trunk_choice import RULE

    p = sub.add_parser(
        "choose-trunk",
        help="choose the untrained trunk's backbone and block on a validation pair",
        description="Evaluate `trunk` (or, with --whitened, `trunk-whitened`) at every candidate backbone "
        f"and block on a validation pair and choose by the rule FDNet's block is chosen: {RULE}. "
        "Prints every candidate's scores; --out writes the choice as YAML, which both trunk methods "
        "take: --method-set trunk:choice=FILE. Use validation frames, never the test frames.",
    )
    p.add_argument("--data", required=True, help="dataset folder with one sub-folder per condition")
    p.add_argument("--reference", required=True, metavar="COND", help="reference condition of the validation pair")
    p.add_argument("--query", required=True, metavar="COND", help="query condition of the validation pair")
    p.add_argument("--frames", metavar="START:END", help="validation frames of both conditions (END exclusive)")
    p.add_argument("--tolerance", type=int, default=0, help="frame tolerance of a correct match (default 0)")
    p.add_argument(
        "--candidates",
        metavar="BACKBONE:BLOCK,...",
        help="candidates in order (ties go to the earlier); lite0/lite1/lite2 abbreviate "
        "efficientnet-lite0..2 (default: blocks 7, 8, 10, 11, 14 of lite0; 10, 12, 14, 17 of "
        "lite1 and lite2)",
    )
    p.add_argument(
        "--input-size",
        type=int,
        nargs=2,
        default=(128, 256),
        metavar=("H", "W"),
        help="image size every candidate reads (default 128 256, FDNet's cpu preset)",
    )
    p.add_argument(
        "--whitened",
        action="store_true",
        help="choose for trunk-whitened (PCA-whitened to --dim); it learns from --fit DIR, else from the "
        "validation pair's reference images",
    )
    p.add_argument("--dim", type=int, default=None, help="with --whitened: L (default 512)")
    p.add_argument("--power", type=float, default=None, help="with --whitened: whitening power (default 1)")
    p.add_argument("--fit", metavar="DIR", help="with --whitened: dataset folder to learn the whitening from")
    p.add_argument("--fit-frames", metavar="START:END", help="with --fit: these frames of every condition")
    p.add_argument("--out", metavar="FILE.yaml", help="write the choice (and every candidate's scores) here")
    from fdnet.cli.common import add_device_argument, add_pipeline_arguments

    add_device_argument(p)
    add_pipeline_arguments(p)
    p.add_argument("--threads", type=thread_count(), help="CPU threads for torch (default: all cores)")
    p.set_defaults(func=run)


def run(args) -> int:
    import logging

    from fdnet.cli.common import check_pipeline_arguments, set_threads
    from fdnet.data.dataset import RouteDataset, parse_frame_range
    from fdnet.data.split import aligned_split
    from fdnet.descriptors.pipeline import PipelineSettings
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable
    from fdnet.methods.fdnet.trunk_choice import DEFAULT_CANDIDATES, choose_trunk, parse_candidates, write_choice

    check_pipeline_arguments(args)
    if not args.whitened and any(v is not None for v in (args.dim, args.power, args.fit, args.fit_frames)):
        raise ConfigError("--dim, --power, --fit and --fit-frames apply to --whitened")
    if args.tolerance < 0:
        raise ConfigError(f"--tolerance must be >= 0, got {args.tolerance}")
    from fdnet.data.images import check_image_size

    check_image_size(args.input_size, "--input-size")
    candidates = parse_candidates(args.candidates or DEFAULT_CANDIDATES)
    if args.out:
        ensure_writable(args.out, what="trunk choice file")
    start, end = parse_frame_range(args.frames)
    conditions = [args.reference, args.query] if args.reference != args.query else [args.reference]
    split = aligned_split(
        RouteDataset.from_folder(args.data, conditions), args.reference, args.query, args.tolerance, start, end
    )
    set_threads(args.threads)
    options = {"device": args.device}
    if args.whitened:
        options.update({"dim": args.dim, "power": args.power, "fit": args.fit, "fit_frames": args.fit_frames})
    log = logging.getLogger(__name__).info  # standard error, as the library's messages (fdnet.logs)
    log(f"{len(candidates)} candidates on {split.description}")
    choice = choose_trunk(
        split,
        candidates,
        tuple(args.input_size),
        whitened=args.whitened,
        options=options,
        pipeline=PipelineSettings(args.batch_size, args.workers),
        log=log,
    )
    if args.frames:
        choice.validation = f"{choice.validation}, frames {args.frames}"
    print(f"{'candidate':<22} {'dim':>6} {'R@1':>6} {'R@5':>6} {'R@100P':>7} {'AUC-PR':>7}")
    for score in choice.scores:
        print(
            f"{score['backbone'] + ':' + str(score['block']):<22} {score['dim']:>6} {score['recall_at_1']:>6.3f} "
            f"{score['recall_at_5']:>6.3f} {score['recall_at_100_precision']:>7.3f} {score['auc_pr']:>7.3f}"
        )
    print(f"chosen: {choice.method} {choice.chosen} at {choice.input_size[0]}x{choice.input_size[1]}")
    if args.out:
        write_choice(args.out, choice)
        print(f"wrote {args.out} (use it with --method {choice.method} --method-set {choice.method}:choice={args.out})")
    return 0
