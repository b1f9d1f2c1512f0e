"""`fdnet loop-closure`: online loop closure over one traverse, frame by frame, against a place
database (:mod:`fdnet.decisions.loop_closure`; docs/loop-closure.md)."""

from __future__ import annotations

import argparse

from fdnet.cli.common import add_device_argument, add_method_arguments, add_pipeline_arguments


def _whole_number(minimum: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from exc
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value

    return parse


def _finite(text: str) -> float:
    import math

    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from exc
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def register(sub) -> None:
    p = sub.add_parser(
        "loop-closure",
        help="online loop closure: read one traverse in order, accept revisits of places already seen",
        description="Read the images of one traverse in fdnet's image order (natural order of file names) as a "
        "robot sees them: describe each frame, score it against the place database except this "
        "traverse's last N frames (single images, or sequences of the last frames), accept its best "
        "place when the acceptance rule's score reaches the threshold, add the frame to the database, "
        "and write one event per accepted closure. A frame's decision uses only frames before it. "
        "See docs/loop-closure.md.",
    )
    _add_traverse_arguments(p)
    add_method_arguments(p)
    p.add_argument(
        "--db",
        help="place database file: one from earlier sessions (`fdnet database build`, or an "
        "earlier loop-closure run), which must hold this method's vectors, or a new file to "
        "create; the traverse's frames are added to it. Default: an in-memory database",
    )
    p.add_argument(
        "--commit-every",
        type=_whole_number(1),
        default=1,
        metavar="N",
        help="frames stored in --db per transaction (default 1: every frame is on disk before the next "
        "is read, one fsync each; N > 1 is faster and changes no decision, but a crash loses up to "
        "N - 1 frames of the database)",
    )
    _add_decision_arguments(p)
    _add_output_arguments(p)
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue a run that was interrupted: --db holds its first frames; their decisions are "
        "replayed from the database, the events files rewritten with them, and the rest processed",
    )
    p.add_argument(
        "--allow-training-frames",
        action="store_true",
        help="with --data: run a trained method on frames it was trained on (refused by default)",
    )
    p.add_argument("--report", metavar="JSON", help="write the run's summary (and evaluation) as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_pipeline_arguments(p, batch_size=16)
    add_device_argument(p)
    p.set_defaults(func=run)


def _add_traverse_arguments(p) -> None:
    """The traverse: a folder, video or bag, or a route's conditions driven one after another."""
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--images", help="the traverse: a folder of images (natural file-name order), a video or " "a ROS bag"
    )
    source.add_argument(
        "--data",
        metavar="DIR",
        help="a route's folder with one sub-folder per condition: drive --conditions one after "
        "another as one traverse, with frame-aligned ground truth (a frame of a later condition "
        "revisits the same frame of every earlier one, within --tolerance)",
    )
    p.add_argument("--conditions", metavar="A,B[,C...]", help="with --data: the conditions, in driving order")
    p.add_argument("--frames", metavar="START:END", help="with --data: the frames of each condition (END exclusive)")
    p.add_argument(
        "--tolerance",
        type=_whole_number(0),
        default=None,
        metavar="N",
        help="with --data: frames within N of the same frame count as a revisit (default 0)",
    )


def _add_decision_arguments(p) -> None:
    """How a frame is decided: the rule, its threshold or calibration, sequences, gates and search."""
    p.add_argument(
        "--exclude-last",
        type=_whole_number(0),
        default=0,
        metavar="N",
        help="also never match this traverse's last N frames, whatever they look like (an extra floor; "
        "by default the robot's recent past is found from the traverse itself, "
        "docs/loop-closure.md)",
    )
    p.add_argument(
        "--accept",
        metavar="RULE",
        help="acceptance rule: raw, margin, ratio, verified, or a score with gates (margin+verified, "
        "margin+floor); default: the calibration's, else margin (docs/loop-closure.md says why)",
    )
    p.add_argument(
        "--accept-set",
        action="append",
        default=[],
        metavar="[RULE:]KEY=VALUE",
        help="a setting of the rule, e.g. margin:radius=5 (repeatable)",
    )
    threshold = p.add_mutually_exclusive_group()
    threshold.add_argument(
        "--calibration",
        metavar="FILE|RUN_DIR",
        help="calibration for this model: gives rule, settings, sequence length, gates and "
        "threshold. Default without --threshold: the one stored in --db (`fdnet calibrate "
        "--db`), else RUN_DIR/loop-calibration.yaml of --checkpoint RUN_DIR (written by "
        "`fdnet loop-closure ... --calibrate-out RUN_DIR`)",
    )
    threshold.add_argument(
        "--threshold", type=_finite, metavar="T", help="accept a closure when the rule's score is at least T"
    )
    p.add_argument(
        "--sequence-length",
        type=_whole_number(1),
        default=None,
        metavar="N",
        help="score sequences of the robot's last N frames (SeqSLAM, causal; 1 = single images); "
        "default: the calibration's, else 10",
    )
    p.add_argument(
        "--gate",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a loop gate setting (repeatable; none/off switches one off): min_brightness, "
        "min_contrast (uninformative frames), still_difference, segment_similarity, "
        "exclude_seconds, exclude_metres (the robot's recent past), consistency, "
        "consistency_window (k consecutive agreeing frames); see docs/loop-closure.md",
    )
    p.add_argument(
        "--search",
        choices=("auto", "exact", "index"),
        default="auto",
        help="how candidates are found: every place (exact), a faiss IVF index that proposes them "
        "(index), or every place up to 20,000 and the index beyond (auto, the default)",
    )


def _add_output_arguments(p) -> None:
    """What the run writes: the events, the evaluation against ground truth, a calibration."""
    p.add_argument(
        "--out",
        required=True,
        metavar="EVENTS_CSV",
        help="CSV of accepted closures, one line each, written as they are accepted",
    )
    p.add_argument("--jsonl", metavar="EVENTS_JSONL", help="the same events as JSON lines")
    p.add_argument(
        "--ground-truth",
        metavar="CSV",
        help="evaluate the run: a ground-truth CSV whose queries are the traverse's frames and whose "
        "references are the database's places (for a new database, the same frames), e.g. "
        "`fdnet groundtruth --positions route.csv route.csv` or a frame list "
        "query_index,reference_indices",
    )
    p.add_argument(
        "--calibrate-out",
        metavar="FILE.yaml|RUN_DIR",
        help="with ground truth (--ground-truth, or --data): choose the threshold of the rule that reaches "
        "--target-precision on this traverse (at 1.0, raised where needed so that fewer than one "
        "wrong closure is expected among 1000 wrong frames) and write it, with p_correct's fit, as "
        "a calibration for later runs "
        "(--calibration FILE; a run directory gets RUN_DIR/loop-calibration.yaml, which runs with "
        "--checkpoint RUN_DIR then use by default); without --threshold this run accepts nothing",
    )
    p.add_argument(
        "--target-precision",
        type=float,
        default=None,
        help="with --calibrate-out: the precision to reach, in (0, 1] (default 1.0)",
    )


def run(args) -> int:
    from fdnet.cli.common import check_pipeline_arguments, create_descriptor, file_options, method_options
    from fdnet.descriptors.pipeline import PipelineSettings
    from fdnet.tasks.loop_closure import LoopClosureRequest, loop_closure

    check_pipeline_arguments(args)
    options = method_options(args, args.method)  # once: the descriptor, the run it reads and the record
    request = LoopClosureRequest(
        events_csv=args.out,
        images=args.images,
        data=args.data,
        conditions=tuple(args.conditions.split(",")) if args.conditions else None,
        frames=args.frames,
        tolerance=args.tolerance,
        db=args.db,
        checkpoint=options.get("checkpoint") if args.method else None,
        calibration=args.calibration,
        threshold=args.threshold,
        accept=args.accept,
        accept_set=tuple(args.accept_set),
        sequence_length=args.sequence_length,
        exclude_last=args.exclude_last,
        gate=tuple(args.gate),
        search=args.search,
        commit_every=args.commit_every,
        events_jsonl=args.jsonl,
        report=args.report,
        ground_truth=args.ground_truth,
        calibrate_out=args.calibrate_out,
        target_precision=args.target_precision,
        resume=args.resume,
        allow_training_frames=args.allow_training_frames,
        pipeline=PipelineSettings(batch_size=args.batch_size, workers=args.workers, progress=not args.no_progress),
        command_line=getattr(args, "command_line", None),
        device=args.device,
    )
    report = loop_closure(
        request, lambda: create_descriptor(args.method, args, options), file_options(args, args.method, options)
    )
    _print_report(args, report)
    if args.report:
        print(f"wrote {args.report}")
    return 0


def _print_report(args, report) -> None:
    """What the run did: closures, the database, the evaluation, the calibration, the gates."""
    print(
        f"wrote {args.out}"
        + (f" and {args.jsonl}" if args.jsonl else "")
        + f": {report.closures} loop closures in {report.frames} frames ({report.rule} >= {report.threshold:g}, "
        f"sequences of {report.sequence_length}"
        + (f", threshold from {report.calibration}" if report.calibration else "")
        + "), "
        f"{report.frames_per_second:.1f} frames/s ({report.seconds:.1f} s)"
    )
    if args.db:
        print(
            f"{args.db}: {report.places_before} places before this traverse, {report.places_after} after"
            + (
                f" ({report.resumed_frames} of its frames stored by the interrupted run, replayed, not added " "again)"
                if report.resumed_frames
                else ""
            )
        )
    if report.evaluation is not None:
        ev = report.evaluation
        m, at = ev["metrics"], ev["at_threshold"]
        print(
            f"evaluated {ev['frames_evaluated']} frames, {ev['frames_with_revisit']} revisiting a searchable place: "
            f"R@100P {m['recall_at_100_precision']:.3f}, R@99P {m['recall_at_99_precision']:.3f}, "
            f"R@95P {m['recall_at_95_precision']:.3f}, P@maxR {m['precision_at_max_recall']:.3f}, "
            f"AUC-PR {m['auc_pr']:.3f}, R@1 {m['recall_at_n']['1']:.3f} (of the revisiting frames)"
        )
        print(
            f"at threshold {at['threshold']:g}: {at['accepted']} accepted, {at['true']} true, {at['false']} false "
            f"(precision {at['precision']:.3f}, recall {at['recall']:.3f})"
        )
        first, back = at["first_pass"], at["revisits"]
        print(
            f"first pass (no place seen before): {first['frames']} frames, {first['accepted']} closures accepted "
            f"(all false); revisits: {back['frames']} frames, {back['true']} closed right, {back['wrong_place']} "
            f"closed to a wrong place, {back['missed']} missed"
        )
        reach = ev["reachable"]
        gated = ", ".join(f"{reason} {count}" for reason, count in reach["gated"].items()) or "none"
        print(
            f"revisits by decision, whatever the threshold: {reach['right_place']} vouched for the right place "
            f"(recall ceiling {reach['recall_ceiling']:.3f}: no threshold recalls more), {reach['wrong_place']} "
            f"for a wrong place, {sum(reach['gated'].values())} held by a gate ({gated})"
            + (f", {reach['held_by_consistency']} by the consistency gate" if reach["held_by_consistency"] else "")
        )
    counts = report.gate_counts
    print(
        f"gates: {counts['uninformative']} uninformative frames skipped, {counts['still_frames']} still frames "
        f"made no decision, {counts['still_exclusion']} frames with the robot's still segment excluded, "
        f"{counts['held_by_consistency']} candidates held back by the consistency gate "
        f"(k={report.gates['consistency']})"
    )
    past = report.recent_past
    if past:
        print(
            f"recent past excluded: median {past['median']:.0f} frames back, 90th percentile "
            f"{past['p90']:.0f}, most {past['max']} ({past['segments']} segment(s): a sequence never spans the start "
            "of a pass or recording)"
        )
    if report.calibrated is not None:
        c = report.calibrated
        print(
            f"wrote {c['path']}: threshold {c['threshold']:.6g} reaches precision {c['precision']:.3f} at recall "
            f"{c['recall']:.3f} on this traverse (target {c['target_precision']:g})"
            + (
                f"; p_correct fitted on {c['p_correct_frames']} frames (at the threshold: "
                f"{c['p_correct_at_threshold']:.3f})"
                if c.get("p_correct_at_threshold") is not None
                else ""
            )
            + "".join(f"; {note}" for note in c["notes"])
        )
    if report.score_drift is not None:
        d = report.score_drift
        print(
            f"warning: {100 * d['share']:.0f} % of the scores rejected on {args.images or args.data} lie above the "
            f"{100 * d['level']:.0f}th percentile of those rejected on the loop of {report.calibration} "
            f"({100 * d['expected']:.0f} % there): its precision may not hold on this route"
        )
