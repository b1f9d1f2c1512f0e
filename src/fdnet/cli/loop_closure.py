"""`fdnet loop-closure`: online loop closure over one traverse, frame by frame, against a place
database (:mod:`fdnet.decisions.loop_closure`; docs/loop-closure.md)."""

from __future__ import annotations

import argparse

from fdnet.cli.common import add_device_argument, add_method_arguments, add_pipeline_arguments


def _whole_number(minimum: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value

    return parse


def _finite(text: str) -> float:
    import math

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def _default_calibration(args):
    """(the calibration to use, the loaded Calibration or None): ``--calibration``; else, without
    ``--threshold``, the one stored in ``--db``, else the one stored in ``--checkpoint RUN_DIR``
    (``loop-calibration.yaml``, else a pair's ``calibration.yaml``:
    :func:`fdnet.decisions.calibration.stored_in_run`); else (None, None). Loaded here so that its
    rule and sequence length become the defaults."""
    from pathlib import Path

    from fdnet.cli.common import method_options
    from fdnet.decisions.calibration import CALIBRATION_FILE, load_calibration, stored_in_run
    from fdnet.decisions.calibration import stored_calibration
    from fdnet.decisions.loop_closure import LOOP_CALIBRATION_FILE

    if args.calibration:  # a file, or a run directory's loop calibration (else its pair calibration)
        from fdnet.decisions.loop_closure import resolve_calibration

        calibrated, source = resolve_calibration(args.calibration, None)
        return source, calibrated
    if args.threshold is not None or args.calibrate_out:
        return None, None
    if args.db and Path(args.db).is_file() and Path(args.db).stat().st_size > 0:
        calibrated, _ = stored_calibration(args.db)
        if calibrated is not None:
            return None, calibrated  # the detector reads it from the database
    checkpoint = method_options(args, args.method).get("checkpoint") if args.method else None
    # the run's loop calibration, else its pair calibration (`calibrate --store-in-run`: used with a warning)
    candidate = stored_in_run(checkpoint, (LOOP_CALIBRATION_FILE, CALIBRATION_FILE)) if checkpoint else None
    if candidate is not None:
        return str(candidate), load_calibration(candidate)
    return None, None


def register(sub) -> None:
    p = sub.add_parser(
        "loop-closure",
        help="online loop closure: read one traverse in order, accept revisits of places already seen",
        description="Read the images of one traverse in fdnet's image order (natural order of file names) as a "
                    "robot sees them: describe each frame, score it against the place database except this "
                    "traverse's last N frames (single images, or sequences of the last frames), accept its best "
                    "place when the acceptance rule's score reaches the threshold, add the frame to the database, "
                    "and write one event per accepted closure. A frame's decision uses only frames before it. "
                    "See docs/loop-closure.md.")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--images", help="the traverse: a folder of images (natural file-name order), a video or "
                                         "a ROS bag")
    source.add_argument("--data", metavar="DIR",
                        help="a route's folder with one sub-folder per condition: drive --conditions one after "
                             "another as one traverse, with frame-aligned ground truth (a frame of a later condition "
                             "revisits the same frame of every earlier one, within --tolerance)")
    p.add_argument("--conditions", metavar="A,B[,C...]", help="with --data: the conditions, in driving order")
    p.add_argument("--frames", metavar="START:END", help="with --data: the frames of each condition (END exclusive)")
    p.add_argument("--tolerance", type=_whole_number(0), default=None, metavar="N",
                   help="with --data: frames within N of the same frame count as a revisit (default 0)")
    add_method_arguments(p)
    p.add_argument("--db", help="place database file: one from earlier sessions (`fdnet database build`, or an "
                                "earlier loop-closure run), which must hold this method's vectors, or a new file to "
                                "create; the traverse's frames are added to it. Default: an in-memory database")
    p.add_argument("--exclude-last", type=_whole_number(0), default=0, metavar="N",
                   help="also never match this traverse's last N frames, whatever they look like (an extra floor; "
                        "by default the robot's recent past is found from the traverse itself, "
                        "docs/loop-closure.md)")
    p.add_argument("--accept", metavar="RULE",
                   help="acceptance rule: raw, margin, ratio, verified, or a score with gates (margin+verified, "
                        "margin+floor); default: the calibration's, else margin (docs/loop-closure.md says why)")
    p.add_argument("--accept-set", action="append", default=[], metavar="[RULE:]KEY=VALUE",
                   help="a setting of the rule, e.g. margin:radius=5 (repeatable)")
    threshold = p.add_mutually_exclusive_group()
    threshold.add_argument("--calibration", metavar="FILE|RUN_DIR",
                           help="calibration for this model: gives rule, settings, sequence length, gates and "
                                "threshold. Default without --threshold: the one stored in --db (`fdnet calibrate "
                                "--db`), else RUN_DIR/loop-calibration.yaml of --checkpoint RUN_DIR (written by "
                                "`fdnet loop-closure ... --calibrate-out RUN_DIR`)")
    threshold.add_argument("--threshold", type=_finite, metavar="T",
                           help="accept a closure when the rule's score is at least T")
    p.add_argument("--sequence-length", type=_whole_number(1), default=None, metavar="N",
                   help="score sequences of the robot's last N frames (SeqSLAM, causal; 1 = single images); "
                        "default: the calibration's, else 10")
    p.add_argument("--out", required=True, metavar="EVENTS_CSV",
                   help="CSV of accepted closures, one line each, written as they are accepted")
    p.add_argument("--jsonl", metavar="EVENTS_JSONL", help="the same events as JSON lines")
    p.add_argument("--ground-truth", metavar="CSV",
                   help="evaluate the run: a ground-truth CSV whose queries are the traverse's frames and whose "
                        "references are the database's places (for a new database, the same frames), e.g. "
                        "`fdnet groundtruth --positions route.csv route.csv` or a frame list "
                        "query_index,reference_indices")
    p.add_argument("--calibrate-out", metavar="FILE.yaml|RUN_DIR",
                   help="with ground truth (--ground-truth, or --data): choose the threshold of the rule that reaches "
                        "--target-precision on this traverse (at 1.0, raised where needed so that fewer than one "
                        "wrong closure is expected among 1000 wrong frames) and write it, with p_correct's fit, as "
                        "a calibration for later runs "
                        "(--calibration FILE; a run directory gets RUN_DIR/loop-calibration.yaml, which runs with "
                        "--checkpoint RUN_DIR then use by default); without --threshold this run accepts nothing")
    p.add_argument("--target-precision", type=float, default=None,
                   help="with --calibrate-out: the precision to reach, in (0, 1] (default 1.0)")
    p.add_argument("--commit-every", type=_whole_number(1), default=1, metavar="N",
                   help="frames stored in --db per transaction (default 1: every frame is on disk before the next "
                        "is read, one fsync each; N > 1 is faster and changes no decision, but a crash loses up to "
                        "N - 1 frames of the database)")
    p.add_argument("--gate", action="append", default=[], metavar="KEY=VALUE",
                   help="a loop gate setting (repeatable; none/off switches one off): min_brightness, "
                        "min_contrast (uninformative frames), still_difference, segment_similarity, "
                        "exclude_seconds, exclude_metres (the robot's recent past), consistency, "
                        "consistency_window (k consecutive agreeing frames); see docs/loop-closure.md")
    p.add_argument("--search", choices=("auto", "exact", "index"), default="auto",
                   help="how candidates are found: every place (exact), a faiss IVF index that proposes them "
                        "(index), or every place up to 20,000 and the index beyond (auto, the default)")
    p.add_argument("--resume", action="store_true",
                   help="continue a run that was interrupted: --db holds its first frames; their decisions are "
                        "replayed from the database, the events files rewritten with them, and the rest processed")
    p.add_argument("--allow-training-frames", action="store_true",
                   help="with --data: run a trained method on frames it was trained on (refused by default)")
    p.add_argument("--report", metavar="JSON", help="write the run's summary (and evaluation) as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_pipeline_arguments(p, batch_size=16)
    add_device_argument(p)
    p.set_defaults(func=run)


def run(args) -> int:
    """The command, holding a lock on each file it writes over the whole run (the events CSV and
    JSON lines, the database): a second run on them, ``--resume`` or not, is refused in one line
    naming the holder before it touches anything (``.NAME.lock`` beside each; the kernel drops a
    killed run's lock)."""
    import contextlib

    from fdnet.io import ensure_writable
    from fdnet.runs.lock import RunLock

    outputs = [(args.out, "events CSV"), (args.jsonl, "events JSON lines"), (args.db, "place database")]
    with contextlib.ExitStack() as locks:
        for path, what in outputs:
            if path:
                ensure_writable(path, what=what)
        for path in sorted({str(path) for path, _ in outputs if path}):
            locks.enter_context(RunLock.for_file(path, getattr(args, "command_line", None) or "fdnet loop-closure"))
        return _run(args)


def _run(args) -> int:
    import json
    from pathlib import Path

    from fdnet.cli.common import check_pipeline_arguments, create_descriptor
    from fdnet.cli.database import _file_options
    import logging

    from fdnet.decisions.loop_closure import LOOP_CALIBRATION_FILE
    from fdnet.decisions.loop_gates import LoopGates
    from fdnet.decisions.loop_settings import LoopClosureSettings, PipelineSettings, TraverseSettings
    from fdnet.decisions.loop_traverse import DEFAULT_RULE, DEFAULT_SEQUENCE_LENGTH, route_traverse, run_traverse
    from fdnet.errors import ConfigError
    from fdnet.data.images import list_images
    from fdnet.io import atomic_write_text, ensure_writable, refuse_writing_an_input
    import os

    from fdnet.matching.database import check_can_create, holds_a_database

    check_pipeline_arguments(args)
    route_flags = [f"--{name}" for name in ("conditions", "frames", "tolerance")
                   if getattr(args, name) is not None]
    if args.images and route_flags:
        raise ConfigError(f"{', '.join(route_flags)} go with --data DIR (a route's conditions), not --images")
    if args.data and not args.conditions:
        raise ConfigError("--data needs --conditions A,B[,...]: the conditions to drive one after another")
    if args.data and args.ground_truth and args.tolerance is not None:
        raise ConfigError("give --tolerance (frame-aligned ground truth) or --ground-truth CSV, not both")
    if args.target_precision is not None and not args.calibrate_out:
        raise ConfigError("--target-precision needs --calibrate-out (the threshold it chooses is written there); "
                          "without it the flag would do nothing")
    gates = LoopGates().with_settings(args.gate) if args.gate else None
    calibration, calibrated = _default_calibration(args)
    rule = args.accept or (None if calibrated is not None else DEFAULT_RULE)
    sequence_length = args.sequence_length
    if sequence_length is None:
        sequence_length = calibrated.sequence_length if calibrated is not None else DEFAULT_SEQUENCE_LENGTH
    # every output path is refused before the first image is described
    for path, what in ((args.out, "events CSV"), (args.jsonl, "events JSON lines"), (args.report, "report JSON")):
        if path:
            ensure_writable(path, what=what)
    if args.db:
        # before any frame: the database's folder takes new files (SQLite writes a journal beside
        # it), an existing database file is writable, a new one could be created there
        ensure_writable(args.db, what="place database")
        if holds_a_database(args.db):
            if not os.access(args.db, os.W_OK):
                raise ConfigError(f"{args.db}: the place database is read-only; loop closure adds every frame to "
                                  "it (copy it somewhere writable, or leave --db out for an in-memory map)")
        else:
            check_can_create(args.db)
    calibrate_out = args.calibrate_out
    if calibrate_out and Path(calibrate_out).is_dir():
        calibrate_out = str(Path(calibrate_out) / LOOP_CALIBRATION_FILE)
    images = args.images
    if args.data:
        images = route_traverse(args.data, args.conditions.split(","), args.frames,
                                0 if args.tolerance is None else args.tolerance)
    else:
        list_images(images)  # its frames are noted as inputs (fdnet.io), checked against every output now
    for path in (args.out, args.jsonl, args.report, args.db, calibrate_out):
        if path:
            refuse_writing_an_input(path)
    descriptor = create_descriptor(args.method, args)
    if args.data:
        from fdnet.evaluation.splits import check_descriptors_held_out

        check_descriptors_held_out([descriptor], args.data, images.conditions, args.frames,
                                   allow=args.allow_training_frames)
    detector = LoopClosureSettings(
        exclude_last=args.exclude_last, rule=rule, rule_settings=args.accept_set or None, threshold=args.threshold,
        calibration=calibration, sequence_length=sequence_length, gates=gates, search=args.search,
        method_options=_file_options(args, args.method), commit_every=args.commit_every)
    settings = TraverseSettings(
        events_csv=args.out, events_jsonl=args.jsonl, detector=detector,
        pipeline=PipelineSettings(batch_size=args.batch_size, workers=args.workers, progress=not args.no_progress),
        ground_truth=args.ground_truth, calibrate_to=calibrate_out,
        target_precision=1.0 if args.target_precision is None else args.target_precision, resume=args.resume)
    report = run_traverse(images, descriptor, args.db, settings, log=logging.getLogger("fdnet.loop_closure").info)
    _print_report(args, report)
    if args.report:
        from fdnet.provenance import provenance

        document = {**report.to_dict(), "provenance": provenance(getattr(args, "command_line", None), device=args.device)}
        atomic_write_text(args.report, json.dumps(document, indent=2, sort_keys=True, default=str) + "\n")
        print(f"wrote {args.report}")
    return 0


def _print_report(args, report) -> None:
    """What the run did: closures, the database, the evaluation, the calibration, the gates."""
    print(f"wrote {args.out}" + (f" and {args.jsonl}" if args.jsonl else "")
          + f": {report.closures} loop closures in {report.frames} frames ({report.rule} >= {report.threshold:g}, "
          f"sequences of {report.sequence_length}" + (f", threshold from {report.calibration}" if report.calibration
                                                       else "") + "), "
          f"{report.frames_per_second:.1f} frames/s ({report.seconds:.1f} s)")
    if args.db:
        print(f"{args.db}: {report.places_before} places before this traverse, {report.places_after} after"
              + (f" ({report.resumed_frames} of its frames stored by the interrupted run, replayed, not added "
                 "again)" if report.resumed_frames else ""))
    if report.evaluation is not None:
        ev = report.evaluation
        m, at = ev["metrics"], ev["at_threshold"]
        print(f"evaluated {ev['frames_evaluated']} frames, {ev['frames_with_revisit']} revisiting a searchable place: "
              f"R@100P {m['recall_at_100_precision']:.3f}, R@99P {m['recall_at_99_precision']:.3f}, "
              f"R@95P {m['recall_at_95_precision']:.3f}, P@maxR {m['precision_at_max_recall']:.3f}, "
              f"AUC-PR {m['auc_pr']:.3f}, R@1 {m['recall_at_n']['1']:.3f} (of the revisiting frames)")
        print(f"at threshold {at['threshold']:g}: {at['accepted']} accepted, {at['true']} true, {at['false']} false "
              f"(precision {at['precision']:.3f}, recall {at['recall']:.3f})")
        first, back = at["first_pass"], at["revisits"]
        print(f"first pass (no place seen before): {first['frames']} frames, {first['accepted']} closures accepted "
              f"(all false); revisits: {back['frames']} frames, {back['true']} closed right, {back['wrong_place']} "
              f"closed to a wrong place, {back['missed']} missed")
    counts = report.gate_counts
    print(f"gates: {counts['uninformative']} uninformative frames skipped, {counts['still_frames']} still frames "
          f"made no decision, {counts['still_exclusion']} frames with the robot's still segment excluded, "
          f"{counts['held_by_consistency']} candidates held back by the consistency gate "
          f"(k={report.gates['consistency']})")
    past = report.recent_past
    if past:
        print(f"recent past excluded: median {past['median']:.0f} frames back, 90th percentile "
              f"{past['p90']:.0f}, most {past['max']} ({past['segments']} segment(s): a sequence never spans the start "
              "of a pass or recording)")
    if report.calibrated is not None:
        c = report.calibrated
        print(f"wrote {c['path']}: threshold {c['threshold']:.6g} reaches precision {c['precision']:.3f} at recall "
              f"{c['recall']:.3f} on this traverse (target {c['target_precision']:g})"
              + (f"; p_correct fitted on {c['p_correct_frames']} frames (at the threshold: "
                 f"{c['p_correct_at_threshold']:.3f})" if c.get("p_correct_at_threshold") is not None else "")
              + "".join(f"; {note}" for note in c["notes"]))
    if report.score_drift is not None:
        d = report.score_drift
        print(f"warning: {100 * d['share']:.0f} % of the scores rejected on {args.images or args.data} lie above the "
              f"{100 * d['level']:.0f}th percentile of those rejected on the loop of {report.calibration} "
              f"({100 * d['expected']:.0f} % there): its precision may not hold on this route")
