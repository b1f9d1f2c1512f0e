"""``fdnet loop-closure``'s work as one library function, :func:`loop_closure`: from what the
command was asked (:class:`LoopClosureRequest`) to the run's
:class:`~fdnet.decisions.loop_traverse.TraverseReport`, with every refusal before the first frame
is described. The command line only parses flags into a request and prints the report.

What it decides that the flags leave open: the calibration (``--calibration``; else, without
``--threshold``, the one stored in the database, else the run's ``loop-calibration.yaml`` or
``calibration.yaml``: :func:`default_calibration`), and from it the rule and the sequence length;
the outputs and the database are checked writable and locked for the whole run, so a second run
on the same files is refused before it touches anything.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from fdnet.decisions.loop_settings import LoopClosureSettings, TraverseSettings
from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.errors import ConfigError

logger = logging.getLogger("fdnet.loop_closure")


@dataclass(frozen=True)
class LoopClosureRequest:
    """What ``fdnet loop-closure`` was asked (its flags, parsed). ``images`` (a folder, video or
    bag) or ``data`` with ``conditions`` (a route driven one condition after another, with
    ``frames`` and ``tolerance``); ``db``: the place database (None: in memory); ``checkpoint``:
    the method's run directory, whose stored calibration is a default; ``calibration`` or
    ``threshold``; ``accept`` (rule) and ``accept_set``; ``sequence_length`` (None: the
    calibration's, else :data:`~fdnet.decisions.loop_traverse.DEFAULT_SEQUENCE_LENGTH`);
    ``gate``: LoopGates settings as KEY=VALUE; the outputs (``events_csv``, ``events_jsonl``,
    ``report``); ``ground_truth``, ``calibrate_out`` and ``target_precision``; ``command_line``
    and ``device`` for the report's provenance."""

    events_csv: str
    images: str | None = None
    data: str | None = None
    conditions: tuple[str, ...] | None = None
    frames: str | None = None
    tolerance: int | None = None
    db: str | None = None
    checkpoint: str | None = None
    calibration: str | None = None
    threshold: float | None = None
    accept: str | None = None
    accept_set: tuple[str, ...] = ()
    sequence_length: int | None = None
    exclude_last: int = 0
    gate: tuple[str, ...] = ()
    search: str = "auto"
    commit_every: int = 1
    events_jsonl: str | None = None
    report: str | None = None
    ground_truth: str | None = None
    calibrate_out: str | None = None
    target_precision: float | None = None
    resume: bool = False
    allow_training_frames: bool = False
    pipeline: PipelineSettings = field(default_factory=PipelineSettings)
    command_line: str | None = None
    device: str | None = None

    def __post_init__(self):
        if (self.images is None) == (self.data is None):
            raise ConfigError("give the traverse as --images PATH or as --data DIR --conditions A,B (one of them)")
        route_flags = [f"--{name}" for name in ("conditions", "frames", "tolerance") if getattr(self, name) is not None]
        if self.images and route_flags:
            raise ConfigError(f"{', '.join(route_flags)} go with --data DIR (a route's conditions), not --images")
        if self.data and not self.conditions:
            raise ConfigError("--data needs --conditions A,B[,...]: the conditions to drive one after another")
        if self.data and self.ground_truth and self.tolerance is not None:
            raise ConfigError("give --tolerance (frame-aligned ground truth) or --ground-truth CSV, not both")
        if self.target_precision is not None and not self.calibrate_out:
            raise ConfigError(
                "--target-precision needs --calibrate-out (the threshold it chooses is written there); "
                "without it the flag would do nothing"
            )
        if self.calibration is not None and self.threshold is not None:
            raise ConfigError("give --calibration or --threshold, not both")


def default_calibration(request: LoopClosureRequest):
    """(the calibration to use, the loaded Calibration or None): ``calibration``; else, without
    ``threshold`` or ``calibrate_out``, the one stored in ``db``, else the one stored in
    ``checkpoint`` (``loop-calibration.yaml``, else a pair's ``calibration.yaml``:
    :func:`fdnet.decisions.calibration.stored_in_run`); else (None, None). Loaded here so that its
    rule and sequence length become the defaults."""
    from fdnet.decisions.calibration import CALIBRATION_FILE, load_calibration, stored_calibration, stored_in_run
    from fdnet.decisions.loop_trust import LOOP_CALIBRATION_FILE, resolve_calibration

    if request.calibration:  # a file, or a run directory's loop calibration (else its pair calibration)
        calibrated, source = resolve_calibration(request.calibration, None)
        return source, calibrated
    if request.threshold is not None or request.calibrate_out:
        return None, None
    if request.db and Path(request.db).is_file() and Path(request.db).stat().st_size > 0:
        calibrated, _ = stored_calibration(request.db)
        if calibrated is not None:
            return None, calibrated  # the detector reads it from the database
    candidate = (
        stored_in_run(request.checkpoint, (LOOP_CALIBRATION_FILE, CALIBRATION_FILE)) if request.checkpoint else None
    )
    if candidate is not None:
        return str(candidate), load_calibration(candidate)
    return None, None


def loop_closure(
    request: LoopClosureRequest, make_descriptor: Callable[[], object], method_options: dict | None = None
):
    """Run ``fdnet loop-closure``: check and lock every output (the events files and the
    database) for the whole run, choose the calibration, rule and sequence length, describe the
    traverse with the descriptor ``make_descriptor()`` makes, and write the events (and the
    report JSON, with provenance). ``method_options``: what rebuilds the descriptor, recorded in
    a database created here. Returns the :class:`~fdnet.decisions.loop_traverse.TraverseReport`."""
    from fdnet.io import ensure_writable
    from fdnet.runs.lock import RunLock

    outputs = [
        (request.events_csv, "events CSV"),
        (request.events_jsonl, "events JSON lines"),
        (request.db, "place database"),
    ]
    with contextlib.ExitStack() as locks:
        for path, what in outputs:
            if path:
                ensure_writable(path, what=what)
        for path in sorted({str(path) for path, _ in outputs if path}):
            locks.enter_context(RunLock.for_file(path, request.command_line or "fdnet loop-closure"))
        return _loop_closure(request, make_descriptor, method_options)


def _loop_closure(request: LoopClosureRequest, make_descriptor, method_options):
    from fdnet.data.images import list_images
    from fdnet.decisions.loop_gates import LoopGates
    from fdnet.decisions.loop_traverse import DEFAULT_RULE, DEFAULT_SEQUENCE_LENGTH, route_traverse, run_traverse
    from fdnet.decisions.loop_trust import LOOP_CALIBRATION_FILE
    from fdnet.io import atomic_write_text, ensure_writable, refuse_writing_an_input
    from fdnet.matching.database import check_can_create, holds_a_database

    gates = LoopGates().with_settings(list(request.gate)) if request.gate else None
    calibration, calibrated = default_calibration(request)
    rule = request.accept or (None if calibrated is not None else DEFAULT_RULE)
    sequence_length = request.sequence_length
    if sequence_length is None:
        sequence_length = calibrated.sequence_length if calibrated is not None else DEFAULT_SEQUENCE_LENGTH
    # every output path is refused before the first image is described
    if request.report:
        ensure_writable(request.report, what="report JSON")
    if request.db:
        # before any frame: the database's folder takes new files (checked with the lock: SQLite
        # writes a journal beside it), an existing database file is writable, a new one could be
        # created there
        if holds_a_database(request.db):
            if not os.access(request.db, os.W_OK):
                raise ConfigError(
                    f"{request.db}: the place database is read-only; loop closure adds every frame to "
                    "it (copy it somewhere writable, or leave --db out for an in-memory map)"
                )
        else:
            check_can_create(request.db)
    calibrate_out = request.calibrate_out
    if calibrate_out and Path(calibrate_out).is_dir():
        calibrate_out = str(Path(calibrate_out) / LOOP_CALIBRATION_FILE)
    images = request.images
    if request.data:
        images = route_traverse(
            request.data,
            list(request.conditions),
            request.frames,
            0 if request.tolerance is None else request.tolerance,
        )
    else:
        list_images(images)  # its frames are noted as inputs (fdnet.io), checked against every output now
    for path in (request.events_csv, request.events_jsonl, request.report, request.db, calibrate_out):
        if path:
            refuse_writing_an_input(path)
    descriptor = make_descriptor()
    if request.data:
        from fdnet.evaluation.splits import check_descriptors_held_out

        check_descriptors_held_out(
            [descriptor], request.data, images.conditions, request.frames, allow=request.allow_training_frames
        )
    detector = LoopClosureSettings(
        exclude_last=request.exclude_last,
        rule=rule,
        rule_settings=list(request.accept_set) or None,
        threshold=request.threshold,
        calibration=calibration,
        sequence_length=sequence_length,
        gates=gates,
        search=request.search,
        method_options=method_options,
        commit_every=request.commit_every,
    )
    settings = TraverseSettings(
        events_csv=request.events_csv,
        events_jsonl=request.events_jsonl,
        detector=detector,
        pipeline=request.pipeline,
        ground_truth=request.ground_truth,
        calibrate_to=calibrate_out,
        target_precision=1.0 if request.target_precision is None else request.target_precision,
        resume=request.resume,
    )
    report = run_traverse(images, descriptor, request.db, settings, log=logger.info)
    if request.report:
        from fdnet.provenance import provenance

        document = {**report.to_dict(), "provenance": provenance(request.command_line, device=request.device)}
        atomic_write_text(request.report, json.dumps(document, indent=2, sort_keys=True, default=str) + "\n")
    return report
