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
    data.add_argument("--tolerance", type=int, default=None,
                      help="frame-aligned ground truth: query frame i matches reference frames i +- N (default 0)")
    data.add_argument("--frames", metavar="START:END", help="calibrate on these frames only (END exclusive)")
    data.add_argument("--filter-frames", action="store_true", help="drop dark and near-duplicate frames first")
    data.add_argument("--dataset-format", metavar="NAME", help="read --data in a published layout (see evaluate)")
    data.add_argument("--split", help="with --dataset-format: a named split or START:END")
    data.add_argument("--format-set", action="append", default=[], metavar="KEY=VALUE",
                      help="with --dataset-format: a protocol setting of the format")
    data.add_argument("--ground-truth", metavar="CSV", help="explicit ground truth instead of frame alignment")
    methods = p.add_argument_group("method")
    add_method_arguments(methods)
    add_pipeline_arguments(methods)
    add_device_argument(methods)
    methods.add_argument("--sequence-length", type=int, default=1,
                         help="calibrate SeqSLAM sequence scores over this many consecutive queries (1 = single "
                              "images); the calibration is then only valid with the same --sequence-length")
    decision = p.add_argument_group("decision")
    decision.add_argument("--accept", default=None, metavar="RULE",
                          help="the acceptance rule (one expression, e.g. margin, ratio, margin+floor; default "
                               "margin)")
    decision.add_argument("--accept-set", action="append", default=[], metavar="[RULE:]KEY=VALUE",
                          help="a setting of the rule (repeatable), e.g. radius=3")
    decision.add_argument("--choose", action="append", default=[], metavar="KEY=V1,V2,...",
                          help="also choose a rule setting on this pair (repeatable), e.g. radius=0,1,2,3,5: every "
                               "value is tried and the one reaching the target with the largest recall is stored")
    decision.add_argument("--target-precision", type=float, default=1.0,
                          help="precision the threshold must reach on the pair, in (0, 1] (default 1.0)")
    out = p.add_argument_group("where to store it (at least one)")
    out.add_argument("--out", metavar="FILE.yaml", help="write the calibration as YAML")
    out.add_argument("--store-in-run", action="store_true",
                     help="write calibration.yaml into the --checkpoint run directory")
    out.add_argument("--db", metavar="MAP.db",
                     help="store it in this place database (built with the same model); `fdnet database query` "
                          "then uses it")
    p.add_argument("--allow-training-frames", action="store_true",
                   help="calibrate a trained method on frames it was trained on (refused by default: its scores "
                        "there are not those of new places)")
    p.set_defaults(func=run)


def _choices(items, accept_set=()) -> dict:
    """``["radius=0,1,3"]`` -> ``{"radius": [0, 1, 3]}`` (values read as YAML, as --accept-set's)."""
    from fdnet.decisions.acceptance import _typed
    from fdnet.errors import ConfigError

    fixed = {item.partition("=")[0].strip().rpartition(":")[2] for item in accept_set}
    out = {}
    for item in items:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or not key or not values.strip():
            raise ConfigError(f"--choose {item!r}: expected KEY=V1,V2,... (e.g. radius=0,1,2,3,5)")
        if key in out:
            raise ConfigError(f"--choose {key} given twice: list every value once, e.g. {key}=0,1,2")
        if key in fixed:
            raise ConfigError(f"--choose {key} and --accept-set {key}: a setting is either fixed or chosen; give one")
        out[key] = [_typed(v.strip()) for v in values.split(",") if v.strip()]
    return out


def _check_choices(spec, choose) -> None:
    """Every value of every --choose setting is valid for the rule, named as the user gave it."""
    from fdnet.decisions.calibration import candidate_specs
    from fdnet.errors import ConfigError

    for key, values in choose.items():
        for value in values:
            try:
                candidate_specs(spec, {key: [value]})
            except ConfigError as exc:
                raise ConfigError(f"--choose {key}={value}: {str(exc).split(': ', 1)[-1]}") from exc
    candidate_specs(spec, choose)  # no values at all


def _rule(args, choose: dict):
    """The acceptance rule of --accept/--accept-set; a setting the rule requires (floor's min) may
    be one that --choose chooses: then it is parsed with the first chosen value."""
    from fdnet.decisions.acceptance import DEFAULT_ACCEPTANCE, parse_acceptance
    from fdnet.errors import ConfigError

    try:
        return parse_acceptance(args.accept or DEFAULT_ACCEPTANCE, args.accept_set)
    except ConfigError as missing:
        from fdnet.decisions.calibration import _yaml_text

        first = [f"{key}={_yaml_text(values[0])}" for key, values in choose.items() if values]
        if not first:
            raise
        try:
            return parse_acceptance(args.accept or DEFAULT_ACCEPTANCE, [*args.accept_set, *first])
        except ConfigError as exc:
            if str(exc) == str(missing):  # the choice was not the missing setting
                raise missing from exc
            raise ConfigError(f"--choose {', '.join(first)}: {str(exc).split(': ', 1)[-1]}") from exc


def _store(calibration, out, run_dir, db, db_path) -> tuple[list, list[str]]:
    """Write the calibration to each place asked for, each even when another fails (a full disk,
    a read-only database): the work is done, so what can be kept is kept, and the rest is
    reported. Returns (the places tried, the failures' messages)."""
    from fdnet.decisions.calibration import CALIBRATION_FILE, DATABASE_KEY, save_calibration
    from fdnet.errors import FdnetError

    writes = []
    if out:
        writes.append((str(out), lambda: save_calibration(calibration, out)))
    if run_dir is not None:
        writes.append((str(run_dir / CALIBRATION_FILE),
                       lambda: save_calibration(calibration, run_dir / CALIBRATION_FILE)))
    if db is not None:
        writes.append((f"{db_path} (database metadata)",
                       lambda: db.set_metadata(DATABASE_KEY, calibration.to_dict(json_safe=True))))
    failed = []
    for where, write in writes:
        try:
            write()
            print(f"wrote {where}")
        except FdnetError as exc:
            failed.append(str(exc))
    return writes, failed


def run(args) -> int:
    import logging
    from pathlib import Path

    from fdnet.cli.common import check_pipeline_arguments, create_descriptor, method_options
    from fdnet.cli.evaluate import split_from_arguments
    from fdnet.decisions.calibration import CALIBRATION_FILE, check_target
    from fdnet.descriptors.pipeline import PipelineSettings
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable
    from fdnet.tasks.calibrate import calibrate

    check_target(args.target_precision)
    choose = _choices(args.choose, args.accept_set)
    spec = _rule(args, choose)
    _check_choices(spec, choose)  # a setting the rule lacks, or a bad value, fails before any work
    if args.tolerance is not None and args.tolerance < 0:
        raise ConfigError(f"--tolerance must be >= 0, got {args.tolerance}")
    if not (args.out or args.store_in_run or args.db):
        raise ConfigError("nothing to store the calibration in: give --out FILE.yaml, --store-in-run and/or "
                          "--db MAP.db")
    check_pipeline_arguments(args)
    run_dir = None
    if args.store_in_run:
        checkpoint = method_options(args, args.method).get("checkpoint")
        if not checkpoint:
            raise ConfigError(f"--store-in-run needs the run directory: --checkpoint RUN_DIR (method {args.method!r} "
                              f"was given none)")
        run_dir = Path(checkpoint)
        if not run_dir.is_dir():
            raise ConfigError(f"--store-in-run: {run_dir} is not a run directory")
        ensure_writable(run_dir / CALIBRATION_FILE, what="calibration in the run directory")
    if args.out:
        ensure_writable(args.out, what="calibration YAML")
    db = None
    descriptor = create_descriptor(args.method, args)
    from fdnet.evaluation.splits import check_descriptors_held_out, default_folder_tolerance

    if args.db:
        from fdnet.matching.database import PlaceDatabase

        db = PlaceDatabase.open(args.db, descriptor=descriptor)  # another model's database: refused now
    try:
        split = split_from_arguments(args)
        check_descriptors_held_out([descriptor], args.data, [split.reference.name, split.query.name], args.frames,
                                   args.dataset_format, args.split, args.allow_training_frames)
        measured_on = {"data_root": str(args.data), "reference": args.reference, "query": args.query,
                       "frames": args.frames, "split": args.split, "dataset_format": args.dataset_format,
                       "tolerance": args.tolerance if args.tolerance is not None or args.dataset_format
                       or args.ground_truth else default_folder_tolerance(args.data, [args.reference, args.query]),
                       "ground_truth": split.description,
                       "ground_truth_file": args.ground_truth}
        measured_on = {k: v for k, v in measured_on.items() if v is not None}
        log = logging.getLogger(__name__).info  # standard error, as the library's messages (fdnet.logs)
        log(f"calibrating {descriptor.name} with rule {spec.name} for precision {args.target_precision:g} on "
            f"{split.description}: {len(split.query)} queries x {len(split.reference)} references")
        calibration = calibrate(descriptor, split, spec, args.target_precision, args.sequence_length,
                                pipeline=PipelineSettings(args.batch_size, args.workers, progress=True), log=log,
                                choose=choose)
        calibration.measured_on.update(measured_on)  # where the data came from, beside what was measured
        print(f"{descriptor.name}, rule {calibration.rule}: threshold {calibration.threshold:.6g} reaches precision "
              f"{calibration.precision:.3f} at recall {calibration.recall:.3f} ({calibration.accepted} of "
              f"{calibration.num_queries} queries accepted; target {calibration.target_precision:g})")
        for note in calibration.notes:
            print(f"note: {note}")
        writes, failed = _store(calibration, args.out, run_dir, db, args.db)
    finally:
        if db is not None:
            db.close()
    if failed:
        if len(failed) == len(writes):  # nothing kept it: the calibration goes to stdout instead
            import yaml

            print("# the calibration, written nowhere (save it as a .yaml file):")
            print(yaml.safe_dump(calibration.to_dict(), sort_keys=False), end="")
        raise ConfigError("; ".join(failed))
    return 0
