"""Calibrate an acceptance rule on an evaluation split: describe the split's images, score every
query with the rule (:mod:`fdnet.decisions.acceptance`) and choose the threshold that reaches a
target precision (:func:`fdnet.decisions.calibration.choose_threshold`). ``fdnet calibrate``'s
work; the :class:`~fdnet.decisions.calibration.Calibration` it returns is what every command
applies."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Callable, Sequence

from fdnet.decisions.acceptance import (
    AcceptanceSpec,
    Candidates,
    decide,
    parse_acceptance,
)
from fdnet.decisions.calibration import (
    CALIBRATION_FILE,
    Calibration,
    candidate_specs,
    check_target,
    choose_threshold,
)
from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.evaluation.experiment import ScoringSettings, evaluate_method
from fdnet.evaluation.splits import SplitSpec
from fdnet.matching.sequence import check_sequence_length
from fdnet.version import __version__


def calibrate(
    descriptor,
    split,
    spec: AcceptanceSpec | str,
    target_precision: float,
    sequence_length: int = 1,
    pipeline: PipelineSettings | None = None,
    log: Callable[[str], None] | None = None,
    choose: dict[str, Sequence] | None = None,
) -> Calibration:
    """Run ``descriptor`` on ``split`` (an :class:`~fdnet.data.split.EvaluationSplit`), score every
    query with ``spec`` and choose the threshold reaching ``target_precision``. ``pipeline``: how
    images are decoded and described (default: batches of 64, no progress bar).

    ``choose`` (e.g. ``{"radius": [0, 1, 2, 3, 5]}``) also chooses rule settings on this split:
    every combination is scored on the same candidates (retrieved once, as deep as the deepest
    needs) and the one whose threshold reaches the target with the largest recall is kept (ties:
    the first listed); the recall of every combination is recorded in the calibration's
    ``measured_on`` (with the split, its ground truth and the sequence length; a caller adds
    where the data came from)."""
    target = check_target(target_precision)
    sequence_length = check_sequence_length(sequence_length)
    if isinstance(spec, str):
        spec = parse_acceptance(spec)
    specs = candidate_specs(spec, choose)
    for candidate in specs:  # e.g. radius_m on image folders: refused before anything is described
        candidate.check_available({"images"}, "calibration on image folders")
    say = log or (lambda message: None)
    deepest = max(specs, key=lambda s: s.depth)
    result = evaluate_method(
        descriptor, split, ScoringSettings(acceptance=[deepest]), pipeline, sequence_length=sequence_length, log=log
    )
    gt = split.ground_truth
    candidates = Candidates(
        result.retrieved,
        result.scores,
        similarity_ceiling=float(descriptor.similarity_ceiling),
        query_paths=result.query_paths,
        reference_paths=result.reference_paths,
    )
    tried = []
    best = None
    for candidate in specs:
        decision = decide(candidate, candidates)
        correct = gt.correct_mask(decision.match[:, None])[:, 0]
        threshold = choose_threshold(decision.score, correct, gt.has_match, target)
        tried.append(
            (
                {
                    k: candidate.settings[n][k]
                    for n, _ in candidate.parts
                    for k in (choose or {})
                    if k in candidate.settings[n]
                },
                threshold,
            )
        )
        if best is None or threshold.recall > best[1].recall:
            best = (candidate, threshold)
    spec, chosen = best
    notes = []
    if choose:
        say(
            "; ".join(
                f"{', '.join(f'{k}={v}' for k, v in values.items())}: recall {t.recall:.3f}" for values, t in tried
            )
            + f" -> chosen {tried[specs.index(spec)][0]}"
        )
    if not math.isfinite(chosen.threshold):
        notes.append(
            f"no threshold reaches precision {target:g} on this split (the most confident query is "
            f"already wrong): nothing will be accepted"
        )
        say(notes[-1])
    where = {
        "data": split.description,
        "ground_truth": gt.description,
        "num_references": int(gt.num_references),
        "sequence_length": int(sequence_length),
    }
    if choose:
        where["chosen_from"] = [{**values, "recall": t.recall, "precision": t.precision} for values, t in tried]
    return Calibration(
        rule=spec.name,
        settings=spec.settings,
        threshold=chosen.threshold,
        target_precision=target,
        precision=chosen.precision,
        recall=chosen.recall,
        accepted=chosen.accepted,
        num_queries=int(gt.num_queries),
        method=descriptor.name,
        fingerprint=descriptor.fingerprint(),
        sequence_length=int(sequence_length),
        measured_on=where,
        created=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        fdnet_version=__version__,
        notes=notes,
    )


def _choices(items, accept_set=()) -> dict:
    """``["radius=0,1,3"]`` -> ``{"radius": [0, 1, 3]}`` (values read as YAML, as --accept-set's)."""
    from fdnet.decisions.acceptance import setting_value
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
        out[key] = [setting_value(v.strip()) for v in values.split(",") if v.strip()]
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


def _rule(accept, accept_set, choose: dict):
    """The acceptance rule of --accept/--accept-set; a setting the rule requires (floor's min) may
    be one that --choose chooses: then it is parsed with the first chosen value."""
    from fdnet.decisions.acceptance import DEFAULT_ACCEPTANCE, parse_acceptance
    from fdnet.errors import ConfigError

    try:
        return parse_acceptance(accept or DEFAULT_ACCEPTANCE, list(accept_set))
    except ConfigError as missing:
        from fdnet.decisions.calibration import yaml_text

        first = [f"{key}={yaml_text(values[0])}" for key, values in choose.items() if values]
        if not first:
            raise
        try:
            return parse_acceptance(accept or DEFAULT_ACCEPTANCE, [*accept_set, *first])
        except ConfigError as exc:
            if str(exc) == str(missing):  # the choice was not the missing setting
                raise missing from exc
            raise ConfigError(f"--choose {', '.join(first)}: {str(exc).split(': ', 1)[-1]}") from exc


def _store(calibration, out, run_dir, db, db_path) -> tuple[list[str], list[str]]:
    """Write the calibration to each place asked for, each even when another fails (a full disk,
    a read-only database): the work is done, so what can be kept is kept, and the rest is
    reported. Returns (the places written, the failures' messages)."""
    from fdnet.decisions.calibration import CALIBRATION_FILE, DATABASE_KEY, save_calibration
    from fdnet.errors import FdnetError

    writes = []
    if out:
        writes.append((str(out), lambda: save_calibration(calibration, out)))
    if run_dir is not None:
        writes.append(
            (str(run_dir / CALIBRATION_FILE), lambda: save_calibration(calibration, run_dir / CALIBRATION_FILE))
        )
    if db is not None:
        writes.append(
            (
                f"{db_path} (database metadata)",
                lambda: db.set_metadata(DATABASE_KEY, calibration.to_dict(json_safe=True)),
            )
        )
    written, failed = [], []
    for where, write in writes:
        try:
            write()
            written.append(where)
        except FdnetError as exc:
            failed.append(str(exc))
    return written, failed


# ---------------------------------------------------------------------- the command
@dataclass(frozen=True)
class CalibrateRequest:
    """What ``fdnet calibrate`` was asked: the validation pair (``split``, as ``fdnet evaluate``
    reads it), the rule (``accept`` with ``accept_set``; ``choose``: KEY=V1,V2 settings chosen on
    the pair), ``target_precision``, ``sequence_length``, where to store the calibration (``out``,
    ``run_dir`` for ``--store-in-run``, ``db``) and how to describe (``pipeline``)."""

    split: SplitSpec
    target_precision: float = 1.0
    accept: str | None = None
    accept_set: tuple = ()
    choose: tuple = ()
    sequence_length: int = 1
    out: str | None = None
    store_in_run: bool = False
    run_dir: str | None = None
    db: str | None = None
    allow_training_frames: bool = False
    pipeline: PipelineSettings = field(default_factory=lambda: PipelineSettings(progress=True))


@dataclass
class CalibrateResult:
    """What :func:`calibrate_command` made and where it was kept (``failed``: the places that
    could not be written, with why)."""

    calibration: Calibration
    written: list
    failed: list


def calibrate_command(request: CalibrateRequest, make_descriptor: Callable[[], object]) -> CalibrateResult:
    """``fdnet calibrate``'s work: every setting and output checked before the method is made,
    the calibration measured on the pair (:func:`calibrate`), what it was measured on recorded,
    and the calibration stored in each place asked for."""
    import logging
    from pathlib import Path

    from fdnet.errors import ConfigError
    from fdnet.evaluation.splits import build_split, check_descriptors_held_out, default_folder_tolerance
    from fdnet.io import ensure_writable

    r, spec_of = request, request.split
    check_target(r.target_precision)
    choose = _choices(r.choose, r.accept_set)
    spec = _rule(r.accept, r.accept_set, choose)
    _check_choices(spec, choose)  # a setting the rule lacks, or a bad value, fails before any work
    if spec_of.tolerance is not None and spec_of.tolerance < 0:
        raise ConfigError(f"--tolerance must be >= 0, got {spec_of.tolerance}")
    if not (r.out or r.store_in_run or r.db):
        raise ConfigError(
            "nothing to store the calibration in: give --out FILE.yaml, --store-in-run and/or " "--db MAP.db"
        )
    run_dir = None
    if r.store_in_run:
        if not r.run_dir:
            raise ConfigError(
                "--store-in-run needs the run directory: --checkpoint RUN_DIR (the method was given " "none)"
            )
        run_dir = Path(r.run_dir)
        if not run_dir.is_dir():
            raise ConfigError(f"--store-in-run: {run_dir} is not a run directory")
        ensure_writable(run_dir / CALIBRATION_FILE, what="calibration in the run directory")
    if r.out:
        ensure_writable(r.out, what="calibration YAML")
    descriptor = make_descriptor()
    db = None
    if r.db:
        from fdnet.matching.database import PlaceDatabase

        db = PlaceDatabase.open(r.db, descriptor=descriptor)  # another model's database: refused now
    try:
        split = build_split(spec_of)
        check_descriptors_held_out(
            [descriptor],
            spec_of.data,
            [split.reference.name, split.query.name],
            spec_of.frames,
            spec_of.dataset_format,
            spec_of.split,
            r.allow_training_frames,
        )
        tolerance = (
            spec_of.tolerance
            if spec_of.tolerance is not None or spec_of.dataset_format or spec_of.ground_truth
            else default_folder_tolerance(spec_of.data, [spec_of.reference, spec_of.query])
        )
        measured_on = {
            "data_root": str(spec_of.data),
            "reference": spec_of.reference,
            "query": spec_of.query,
            "frames": spec_of.frames,
            "split": spec_of.split,
            "dataset_format": spec_of.dataset_format,
            "tolerance": tolerance,
            "ground_truth": split.description,
            "ground_truth_file": spec_of.ground_truth,
        }
        log = logging.getLogger(__name__).info  # standard error, as the library's messages (fdnet.logs)
        log(
            f"calibrating {descriptor.name} with rule {spec.name} for precision {r.target_precision:g} on "
            f"{split.description}: {len(split.query)} queries x {len(split.reference)} references"
        )
        calibration = calibrate(
            descriptor, split, spec, r.target_precision, r.sequence_length, pipeline=r.pipeline, log=log, choose=choose
        )
        # where the data came from, beside what was measured
        calibration.measured_on.update({k: v for k, v in measured_on.items() if v is not None})
        written, failed = _store(calibration, r.out, run_dir, db, r.db)
    finally:
        if db is not None:
            db.close()
    return CalibrateResult(calibration, written, failed)
