"""A whole traverse through the loop-closure detector: what ``fdnet loop-closure`` runs.

:func:`run_traverse` reads one traverse (a folder, video or ROS bag, or a route's conditions
driven one after another: :func:`route_traverse`), describes its frames in batches (their pixel
signals for the gates come from the same decoded images), feeds them to a
:class:`~fdnet.decisions.loop_closure.LoopClosureDetector`, writes each accepted closure as it is
accepted (:class:`~fdnet.decisions.loop_events.EventLog`), resumes an interrupted run, and
evaluates and calibrates on ground truth (:mod:`fdnet.decisions.loop_evaluation`).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from fdnet.decisions.loop_closure import LoopClosureDetector
from fdnet.decisions.loop_evaluation import calibrate_decisions, evaluate_decisions
from fdnet.decisions.loop_events import EventLog
from fdnet.decisions.loop_gates import frame_signals
from fdnet.decisions.loop_settings import TraverseSettings
from fdnet.errors import ConfigError, DataError
from fdnet.matching.database.storage import place_name

#: What ``fdnet loop-closure`` does when given no rule and no sequence length, chosen on the
#: development loops (Nordland summer then winter, Gardens Point day -> night -> day;
#: docs/loop-closure.md has the table): on Nordland single images reach R@100P 0.004 at best for
#: every descriptor and 5-frame sequences 0.004, where 10-frame sequences under the margin rule
#: reach 0.724 with FDNet; on Gardens Point single images 0.145 against 0.220.
DEFAULT_RULE = "margin"
DEFAULT_SEQUENCE_LENGTH = 10


@dataclass
class RouteTraverse:
    """A route's conditions driven one after another as one traverse: the frames in order, the
    condition and frame id of each, and its ground truth (a frame of a later condition revisits
    the frames of every earlier condition whose frame id is within ``tolerance``)."""

    paths: list[Path]
    conditions: list[str]
    condition_of: np.ndarray
    frame_ids: np.ndarray
    tolerance: int
    description: str

    def ground_truth(self, places_before: int = 0):
        """Ground truth whose queries are the traverse's frames and whose references are the
        database's places (``places_before`` places from earlier sessions first)."""
        from fdnet.data.groundtruth import GroundTruth

        positives: list = []
        for i in range(len(self.conditions)):
            # the conditions are consecutive blocks: the earlier ones are the frames before this one
            block = np.flatnonzero(self.condition_of == i)
            if block[0] == 0:
                positives += [np.zeros(0, np.int64)] * len(block)
                continue
            aligned = GroundTruth.from_frames(self.frame_ids[block], self.frame_ids[: block[0]], self.tolerance)
            positives += [p + places_before for p in aligned.positives]
        return GroundTruth(
            positives,
            places_before + len(self.paths),
            f"{self.description}: a frame revisits the frames of earlier conditions within " f"{self.tolerance} frames",
        )


def route_traverse(
    data: str | os.PathLike, conditions: Sequence[str], frames: str | None = None, tolerance: int = 0
) -> RouteTraverse:
    """The conditions of the route in ``data`` (``DATA/<condition>/`` folders, videos or bags,
    frame-aligned) driven one after another, each cut to ``frames`` (``START:END``), as one
    traverse with frame-aligned ground truth (:class:`RouteTraverse`)."""
    from fdnet.data.dataset import RouteDataset, parse_frame_range

    conditions = [c.strip() for c in conditions if c.strip()]
    if len(conditions) < 2:
        raise ConfigError(
            f"--conditions needs at least two conditions to drive one after another (the first "
            f"pass and a revisit), got {','.join(conditions) or 'none'}"
        )
    if len(set(conditions)) != len(conditions):
        raise ConfigError(f"--conditions names a condition twice: {','.join(conditions)}")
    if isinstance(tolerance, bool) or not isinstance(tolerance, int) or tolerance < 0:
        raise ConfigError(f"--tolerance must be a whole number of frames of at least 0, got {tolerance!r}")
    dataset = RouteDataset.from_folder(data, conditions).frames(*parse_frame_range(frames))
    sizes = {c: len(dataset[c]) for c in conditions}
    if min(sizes.values()) == 0:
        empty = next(c for c, n in sizes.items() if n == 0)
        raise DataError(f"{Path(data) / empty}: no frames" + (f" in the range {frames}" if frames else ""))
    paths, which, ids = [], [], []
    for i, condition in enumerate(conditions):
        traverse = dataset[condition]
        paths += traverse.paths
        which += [i] * len(traverse)
        ids += list(traverse.frame_ids)
    where = f"{Path(data).name} {' -> '.join(conditions)}" + (f", frames {frames}" if frames else "")
    return RouteTraverse(paths, conditions, np.array(which), np.array(ids, dtype=np.int64), tolerance, where)


@dataclass
class TraverseReport:
    """What :func:`run_traverse` did: frames, closures, time, the database and the evaluation."""

    frames: int
    closures: int
    seconds: float
    places_before: int
    places_after: int
    rule: str
    rule_settings: dict
    threshold: float
    sequence_length: int
    exclude_last: int
    database: str
    events: list[str]
    gates: dict = field(default_factory=dict)
    #: what the gates did: uninformative frames, frames with a still-robot exclusion, candidates
    #: held back by the consistency gate
    gate_counts: dict = field(default_factory=dict)
    #: how far back each frame's exclusion of the robot's recent past reached (frames): median,
    #: 90th percentile, largest, a histogram, and the segments the traverse was cut into
    recent_past: dict = field(default_factory=dict)
    #: this run's scores against its calibration's (set when they departed from them)
    score_drift: dict | None = None
    #: frames of an interrupted run taken over from the database (replayed, not described again)
    resumed_frames: int = 0
    evaluation: dict | None = None
    calibration: str | None = None
    #: the calibration this run wrote (``calibrate_to``): path, threshold, precision, recall
    calibrated: dict | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def frames_per_second(self) -> float:
        described = self.frames - self.resumed_frames
        return described / self.seconds if self.seconds > 0 else float("nan")

    def to_dict(self) -> dict:
        out = asdict(self)
        out["frames_per_second"] = self.frames_per_second
        return out


def run_traverse(
    images,
    descriptor,
    database=None,
    settings: TraverseSettings | None = None,
    log: Callable[[str], None] | None = None,
) -> TraverseReport:
    """Run a :class:`LoopClosureDetector` over one traverse, writing each accepted closure to
    ``settings.events_csv`` (and ``events_jsonl``) as it is accepted.

    ``images``: a folder (or video or ROS bag: its frames bring their timestamps, and a bag's its
    positions, for ``radius_s`` / ``radius_m`` and the gates' seconds / metres), in fdnet's one
    image order, or a :class:`RouteTraverse` (a route's conditions one after another, which
    brings its own ground truth). ``database``: a place-database file from earlier sessions (or a
    new file to create; None = in memory only). ``settings``: a
    :class:`~fdnet.decisions.loop_settings.TraverseSettings`: the detector's settings, the
    outputs, the ground truth (a CSV of :class:`~fdnet.data.groundtruth.GroundTruth` whose
    queries are the frames and whose references are the database's places; the run is then
    evaluated by :func:`~fdnet.decisions.loop_evaluation.evaluate_decisions`), the calibration
    to write (without a threshold or calibration such a run accepts nothing: threshold +inf),
    and ``resume`` (replay the frames an interrupted run stored from their vectors: nothing is
    described or stored twice; rewrite the events they accepted, go on with the rest). Every
    refusal (paths, rule, calibration, ground truth, database) comes before the first frame is
    described.
    """
    from fdnet.data.groundtruth import GroundTruth

    if not isinstance(settings, TraverseSettings):
        raise ConfigError(f"run_traverse needs TraverseSettings (at least events_csv), got {type(settings).__name__}")
    say = log or (lambda message: None)
    route = images if isinstance(images, RouteTraverse) else None
    ground_truth, calibrate_to = settings.ground_truth, settings.calibrate_to
    detector_settings = _checked_settings(settings, route, database)
    paths, where, names, times, positions = _traverse_frames(images, route)
    with LoopClosureDetector(descriptor, database, detector_settings) as detector:
        db = detector.database
        done = _frames_done(db, detector.map.names, names, settings.resume)
        places_before = detector.places - done
        truth = None
        if ground_truth is not None:
            truth = GroundTruth.from_csv(
                ground_truth, num_references=places_before + len(paths), num_queries=len(paths)
            )
            truth.check_names(paths, [*detector.map.names[:places_before], *paths])
        elif route is not None:
            truth = route.ground_truth(places_before)
        if truth is not None:
            _check_searchable_revisit(truth, places_before, detector.exclude_last, detector.sequence_length)
        # a rule that looks at the images (verification) refuses unusable ones (too small for
        # local features) before the first frame is described
        detector.spec.check_images(paths, [*detector.map.names[:places_before], *names])
        initial = []
        if done:
            last = _signals_of(paths[done - 1 : done], descriptor)
            initial = detector.resume(done, last_thumbnail=last.thumbnails[0])
            say(
                f"resuming {where}: {done} of {len(paths)} frames were stored by the interrupted run "
                f"({len(initial)} closures among them); continuing with frame {done}"
            )
        say(
            f"loop closure over {len(paths)} frames of {where} with {descriptor.name}, rule {detector.spec.name} "
            f"(threshold {detector.threshold:g}), {places_before} places in {db.path} before the run"
        )
        t0 = time.perf_counter()
        starts = set() if route is None else {int(i) for i in np.flatnonzero(np.diff(route.condition_of)) + 1}
        frames = TraverseFrames(paths, names, times, positions, frozenset(starts))
        events = _detect_over(detector, frames, settings, start=done, initial=initial)
        detector.flush()
        seconds = time.perf_counter() - t0
        report = _report(detector, seconds, places_before, events, done, detector_settings.calibration)
        if truth is not None:
            report.evaluation = evaluate_decisions(detector.decisions, truth, detector.threshold, detector.spec.name)
        if calibrate_to is not None:
            source = {
                "images": where if route is not None else str(Path(images).resolve()),
                **(
                    {"ground_truth_file": str(Path(ground_truth).resolve())}
                    if ground_truth is not None
                    else {"ground_truth": truth.description}
                ),
            }
            report.calibrated = _calibrate_on_traverse(detector, truth, settings.target_precision, source, calibrate_to)
    return report


def _checked_settings(settings: TraverseSettings, route, database):
    """Refuse what cannot work before any frame is read (outputs, calibration target, resuming
    without a file); the detector's settings (threshold +inf when calibrating without one)."""
    from fdnet.io import ensure_writable

    detector_settings = settings.detector
    if settings.calibrate_to is not None:
        from fdnet.decisions.calibration import check_target

        if settings.ground_truth is None and route is None:
            raise ConfigError(
                "calibrating on a traverse needs its ground truth (--ground-truth CSV, or a route "
                "given as --data DIR --conditions A,B)"
            )
        check_target(settings.target_precision)
        ensure_writable(settings.calibrate_to, what="calibration file")
        if detector_settings.threshold is None and detector_settings.calibration is None:
            detector_settings = replace(detector_settings, threshold=math.inf)
    for path, what in ((settings.events_csv, "events CSV"), (settings.events_jsonl, "events JSON lines")):
        if path is not None:
            ensure_writable(path, what=what)
    if settings.resume and database is None:
        raise ConfigError(
            "resuming needs the place database the interrupted run wrote (--db FILE): an in-memory "
            "run keeps nothing to resume from"
        )
    return detector_settings


def _report(
    detector: LoopClosureDetector, seconds: float, places_before: int, events: EventLog, resumed: int, calibration
) -> TraverseReport:
    return TraverseReport(
        frames=detector.frames,
        closures=len(detector.closures),
        seconds=seconds,
        places_before=places_before,
        places_after=detector.places,
        rule=detector.spec.name,
        rule_settings=detector.spec.settings,
        threshold=detector.threshold,
        sequence_length=detector.sequence_length,
        exclude_last=detector.exclude_last,
        database=str(detector.database.path),
        events=[str(p) for p in events.paths],
        gates=detector.gates.to_dict(),
        gate_counts=dict(detector.gate_counts),
        resumed_frames=resumed,
        recent_past=recent_past_summary(detector),
        score_drift=detector.drift,
        calibration=None if calibration is None else str(calibration),
    )


def recent_past_summary(detector: LoopClosureDetector) -> dict:
    """How far back the detector's exclusion of the robot's recent past reached, over the frames
    of this traverse: median, 90th percentile, largest, and a histogram (frames back -> count,
    in bins of 5)."""
    back = np.asarray(detector.excluded_back, dtype=np.int64)
    if not len(back):
        return {}
    bins = np.bincount(back // 5)
    return {
        "median": float(np.median(back)),
        "p90": float(np.percentile(back, 90)),
        "max": int(back.max()),
        "histogram": {f"{5 * i}-{5 * i + 4}": int(n) for i, n in enumerate(bins) if n},
        "segments": int(detector.segments),
    }


def _check_searchable_revisit(truth, places_before: int, exclude_last: int, length: int) -> None:
    """Refuse, before the first frame is described, ground truth in which no frame revisits a
    place it could ever search (its true places all within its own recent past): nothing could be
    evaluated, and a run would store every frame before saying so."""
    if truth.num_queries != 0 and any(
        len(p) and int(p.min()) < places_before + max(q - exclude_last - (length - 1), 0)
        for q, p in enumerate(truth.positives)
    ):
        return
    raise DataError(
        f"no frame of the traverse revisits a place it could search ({truth.description}; frames "
        f"after exclude-last {exclude_last} and the sequence's {length - 1} more): nothing to evaluate. "
        "Does the traverse return to a place it saw before?"
    )


def _traverse_frames(images, route: RouteTraverse | None):
    """(paths, description, place names, timestamps, positions) of the traverse's frames, the
    names checked before any frame is described."""
    from fdnet.data.frame_records import frame_records, positions_in_metres
    from fdnet.data.images import list_images
    from fdnet.matching.database import check_place_names

    paths = list(route.paths) if route is not None else list_images(images)
    where = route.description if route is not None else str(images)
    names = [place_name(p) for p in paths]
    if len(set(names)) != len(names):
        seen = set()
        twice = next(n for n in names if n in seen or seen.add(n))
        raise DataError(f"{twice}: listed twice in this traverse; every frame is a place under its own name")
    check_place_names(names)  # the database could not store them
    # frames of a video or bag carry their time, and a bag's its position: radius_s / radius_m use them
    records = frame_records(paths)
    return paths, where, names, [r.timestamp for r in records], positions_in_metres(records)


def _frames_done(db, places, names: list[str], resume: bool) -> int:
    """How many of the traverse's frames an interrupted run stored (with ``resume``), checking
    that they are its first frames and the database's last places (``places``: the names of the
    detector's map, which holds them: the database handed them over); a traverse already in the
    database without ``resume`` is refused."""
    already = db.existing_names(names)
    if not already:
        return 0
    first = next(n for n in names if n in already)
    if not resume:
        raise DataError(
            f"{db.path}: already holds {len(already)} of these {len(names)} frames (e.g. {first}); "
            "a traverse is added once: to continue an interrupted run give --resume, otherwise use a "
            "copy of the database from before that run, or another database"
        )
    done = len(already)
    stored = places[len(places) - done :]
    if stored != names[:done]:
        raise DataError(
            f"{db.path}: holds {done} of these frames, but not as the first {done} frames of this "
            "traverse stored last (another traverse was added after them, or the frames changed "
            "order): it cannot be resumed; use a copy of the database from before the run"
        )
    return done


def _signals_of(paths, descriptor):
    """The pixel signals of a few frames, decoded as the descriptor gets them."""
    from fdnet.descriptors.pipeline import iter_image_batches

    uint8 = descriptor.accepts_uint8
    for _, images in iter_image_batches(paths, descriptor.input_size, len(paths), uint8=uint8, workers=0):
        return frame_signals(images)
    raise DataError("no frame to read")


@dataclass(frozen=True)
class TraverseFrames:
    """The frames of a traverse in order: paths, place names, timestamps and positions (None
    where unknown), and the frames that start a new recording."""

    paths: list
    names: list
    times: list
    positions: list
    segment_starts: frozenset = frozenset()


def _detect_over(
    detector: LoopClosureDetector, frames: TraverseFrames, settings: TraverseSettings, start: int = 0, initial=()
) -> EventLog:
    """Describe ``frames.paths[start:]`` a batch at a time (with each frame's pixel signals) and
    feed each to ``detector``, writing each accepted closure to the event log as it is accepted
    (the log starts from the ``initial`` events of a resumed run); returns the (closed) log."""
    from fdnet.descriptors.pipeline import DescribeJob, PipelineSettings, describe_stream

    descriptor, pipeline = detector.descriptor, settings.pipeline

    def describe(images):
        return descriptor.describe(images), frame_signals(images)

    bar = None
    if pipeline.progress:
        from fdnet.progress import progress_bar

        bar = progress_bar(
            total=len(frames.paths),
            initial=start,
            desc=f"loop closure [{descriptor.name}]",
            unit="frame",
            smoothing=0.1,
        )
    try:
        with EventLog(settings.events_csv, settings.events_jsonl, initial=initial) as events:
            # the stream shows no bar of its own: this loop's counts frames and closures
            quiet = PipelineSettings(pipeline.batch_size, pipeline.workers, progress=False)
            for offset, (vectors, signals) in describe_stream(
                descriptor, frames.paths[start:], quiet, DescribeJob(describe)
            ):
                vectors = np.asarray(vectors, dtype=np.float32)
                for i, vector in enumerate(vectors):
                    k = start + offset + i
                    detector.look_ahead(vectors[i + 1 :])
                    closure = detector.process_vector(
                        vector,
                        name=frames.names[k],
                        timestamp=frames.times[k],
                        position=frames.positions[k],
                        signals=signals[i],
                        new_segment=k in frames.segment_starts,
                    )
                    if closure is not None:
                        events.write(closure)
                if bar is not None:
                    bar.update(len(vectors))
                    bar.set_postfix(closures=events.count, refresh=False)
    finally:
        if bar is not None:
            bar.close()
    return events


def _calibrate_on_traverse(
    detector: LoopClosureDetector, truth, target_precision: float, source: dict, calibrate_to
) -> dict:
    """Choose the threshold reaching ``target_precision`` on this traverse's decisions, write it
    to ``calibrate_to`` and return what :attr:`TraverseReport.calibrated` records."""
    from fdnet.decisions.calibration import save_calibration

    calibrated = calibrate_decisions(detector.decisions, truth, detector, target_precision, source)
    written = save_calibration(calibrated, calibrate_to)
    fitted = calibrated.probability or {}
    at = float(calibrated.p_correct([calibrated.threshold])[0]) if math.isfinite(calibrated.threshold) else None
    return {
        "path": str(written),
        "threshold": calibrated.threshold,
        "target_precision": calibrated.target_precision,
        "p_correct_frames": int(fitted.get("frames", 0)),
        "p_correct_at_threshold": at if at is not None and math.isfinite(at) else None,
        "precision": calibrated.precision,
        "recall": calibrated.recall,
        "accepted": calibrated.accepted,
        "notes": list(calibrated.notes),
    }
