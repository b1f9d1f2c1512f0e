"""Online loop closure: a robot's traverse, frame by frame, against a persistent place database.

For each new frame, :class:`LoopClosureDetector`:

1. describes it (or takes its vector);
2. scores it against the places in the database *except this traverse's last ``exclude_last``
   frames* (a robot's previous few frames always look like its current one and are no revisit):
   the single-image similarity, or with ``sequence_length`` > 1 the SeqSLAM sequence similarity
   over the robot's last frames (:func:`fdnet.matching.sequence.online_sequence_scores`);
3. ranks those places and turns the candidates into one acceptance score with a named rule of
   :mod:`fdnet.decisions.acceptance` (``raw``, ``margin``, ``ratio``, gates such as ``floor``,
   and geometric verification ``verified`` from :mod:`fdnet.decisions.verification`, e.g.
   ``margin+verified``);
4. accepts the best candidate as a loop closure when that score reaches the threshold (given, or
   from a calibration file of :mod:`fdnet.decisions.calibration` made for the same model);
5. adds the frame to the database (one transaction, see :mod:`fdnet.matching.database`) and
   returns the :class:`Closure`, or None.

**Causal.** Every number a frame's decision uses comes from that frame and frames processed
before it: the places searched were added before it, the sequence rows are those of earlier
frames as they were computed then, and nothing is revised later. So the events up to frame t do
not depend on frames after t (a test changes the future frames and gets the same events).

**Search.** The database file is the map that persists between sessions; the detector keeps the
database's vectors in memory as well (read once when it starts, then appended as it adds frames)
and scores the new frame against all of them exhaustively, because sequence scores need each
frame's whole similarity row, not a top-k. Cost per frame is one (places x dim) product:
milliseconds for 10^4 places; an approximate index would be needed for maps of 10^6.

:func:`run_traverse` is what ``fdnet loop-closure`` calls: a folder of images in fdnet's one
order, events written as they are accepted (:class:`EventLog`), and optionally an evaluation
against ground truth with the metrics of :mod:`fdnet.evaluation.metrics`.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
import time
import uuid
from collections import deque
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from fdnet.decisions.acceptance import AcceptanceSpec, Candidates, decide, parse_acceptance
from fdnet.errors import ConfigError, DataError
from fdnet.io import spreadsheet_text

logger = logging.getLogger(__name__)

#: columns of the events CSV, in order (the JSON lines carry the same keys)
EVENT_COLUMNS = ("query_index", "query", "match_index", "match", "score", "similarity", "rule", "threshold",
                 "timestamp", "match_timestamp")


@dataclass(frozen=True)
class Closure:
    """One accepted loop closure: frame ``query_index`` of this traverse (named ``query``) is
    place ``match_index`` of the database (named ``match``), with acceptance ``score`` under
    ``rule`` (>= ``threshold``) and the raw (or sequence) ``similarity`` of the pair."""

    query_index: int
    query: str
    match_index: int
    match: str
    score: float
    similarity: float
    rule: str
    threshold: float
    timestamp: float | None = None
    match_timestamp: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class FrameDecision:
    """What the detector decided for one frame, accepted or not (for evaluation): the candidate
    its rule vouches for (``match`` -1 when nothing was searchable yet), the acceptance ``score``
    (NaN without a candidate; -inf when a gate rejected it) and how many places were searchable
    (the places the frame could have matched: indices 0..searchable-1)."""

    query_index: int
    match: int
    score: float
    accepted: bool
    searchable: int
    #: the best place by (sequence) similarity and that similarity (the ranking, for Recall@1)
    best: int = -1
    best_similarity: float = float("nan")


class _Vectors:
    """The database's vectors in memory, appended a row at a time (capacity doubles, so adding
    N rows copies O(N) rows in all, where np.vstack per frame would copy O(N^2))."""

    def __init__(self, dim: int, initial: np.ndarray | None = None):
        rows = np.zeros((0, dim), np.float32) if initial is None else np.asarray(initial, np.float32)
        self._data = np.empty((max(1024, 2 * len(rows)), dim), dtype=np.float32)
        self._data[:len(rows)] = rows
        self._count = len(rows)

    def __len__(self) -> int:
        return self._count

    def append(self, row: np.ndarray) -> None:
        if self._count == len(self._data):
            grown = np.empty((2 * len(self._data), self._data.shape[1]), dtype=np.float32)
            grown[:self._count] = self._data[:self._count]
            self._data = grown
        self._data[self._count] = row
        self._count += 1

    def view(self, count: int | None = None) -> np.ndarray:
        return self._data[:self._count if count is None else count]


def _stored_calibration(database):
    """(the calibration ``fdnet calibrate --db`` stored in the database, where it came from), or
    (None, None) when the database (a PlaceDatabase or an existing file) holds none."""
    from fdnet.decisions.calibration import DATABASE_KEY, Calibration
    from fdnet.matching.database import MEMORY, PlaceDatabase

    if isinstance(database, PlaceDatabase):
        stored, path = database.get_metadata(DATABASE_KEY), database.path
    elif database is not None and str(database) != MEMORY and Path(database).is_file():
        with PlaceDatabase.open(database) as db:
            stored, path = db.get_metadata(DATABASE_KEY), db.path
    else:
        return None, None
    if stored is None:
        return None, None
    source = f"{path} (its stored calibration)"
    return Calibration.from_dict(stored, source=source), source


def _load_calibration(calibration, descriptor, sequence_length: int, source: str | None = None):
    """A :class:`~fdnet.decisions.calibration.Calibration` (or the path of its file, or a run
    directory holding one), refused when it was made for another model or sequence length."""
    from fdnet.decisions.calibration import Calibration, load_calibration

    source = source or "calibration"
    if not isinstance(calibration, Calibration):
        source = str(calibration)
        calibration = load_calibration(calibration)
    # the calibration counts single images as sequence length 0
    calibration.check(descriptor=descriptor, sequence_length=sequence_length if sequence_length > 1 else 0,
                      source=source)
    return calibration, source


_BLAS = None


def _single_blas_thread():
    """A context in which numpy's BLAS runs one thread (threadpoolctl, the controller made once:
    making it per frame would cost more than the product)."""
    global _BLAS
    if _BLAS is None:
        from threadpoolctl import ThreadpoolController

        _BLAS = ThreadpoolController()
    return _BLAS.limit(limits=1, user_api="blas")


class LoopClosureDetector:
    """Online loop-closure detection over a place database (see the module docstring).

    ``descriptor``: a :mod:`fdnet.descriptors` method. ``database``: a
    :class:`~fdnet.matching.database.PlaceDatabase` (e.g. from earlier sessions), a path (opened
    when the file exists, else created), or None (a scratch database in memory); its vectors
    must come from ``descriptor`` (same fingerprint). ``exclude_last``: how many of this
    traverse's most recent frames are never candidates. ``rule``: an acceptance expression
    (``"margin"``, ``"margin+verified"``) or a parsed :class:`AcceptanceSpec`, with
    ``rule_settings`` (``{"radius": 5}`` or ``["margin:radius=5"]``); ``threshold``: the score
    at which a candidate is accepted; or ``calibration``: a calibration file giving rule,
    settings and threshold for this model. ``sequence_length``: score by sequences of the
    robot's last N frames (1 = single images). Without threshold and calibration, the
    calibration stored in the database (``fdnet calibrate --db``) is used. ``method_options``:
    what rebuilds the descriptor, recorded in a database created here. ``allow_duplicates``: add
    a frame whose name the database already holds (default: refuse it, it was added in an
    earlier run). ``commit_every``: frames stored per database transaction; 1 (default) makes
    every frame durable before :meth:`process` returns (one fsync per frame); N > 1 stores them
    N at a time (the rest at :meth:`flush`/:meth:`close`), which changes no decision (the
    detector searches its own copy of the vectors) but a crash loses up to N - 1 frames.
    """

    def __init__(self, descriptor, database=None, *, exclude_last: int, rule: str | AcceptanceSpec | None = None,
                 rule_settings=None, threshold: float | None = None, calibration=None, sequence_length: int = 1,
                 method_options: dict | None = None, allow_duplicates: bool = False, commit_every: int = 1):
        from fdnet.matching.database import PlaceDatabase

        if isinstance(exclude_last, bool) or not isinstance(exclude_last, (int, np.integer)) or exclude_last < 0:
            raise ConfigError(f"exclude-last must be a whole number of at least 0, got {exclude_last!r}")
        if isinstance(sequence_length, bool) or not isinstance(sequence_length, (int, np.integer)) \
                or sequence_length < 1:
            raise ConfigError(f"sequence length must be a whole number of at least 1, got {sequence_length!r}")
        if isinstance(commit_every, bool) or not isinstance(commit_every, (int, np.integer)) or commit_every < 1:
            raise ConfigError(f"commit-every must be a whole number of at least 1, got {commit_every!r}")
        if getattr(descriptor, "needs_fit", False):
            raise ConfigError(f"method {descriptor.name!r} must be given what it learns from (--fit DIR, or dbow's "
                              "--vocabulary) before it can describe frames online")
        self.descriptor = descriptor
        self.exclude_last = int(exclude_last)
        self.sequence_length = int(sequence_length)
        self.allow_duplicates = bool(allow_duplicates)
        self.commit_every = int(commit_every)
        # frames decided but not yet stored (commit_every > 1): vectors, names, positions, metadata
        self._pending: list[tuple] = []
        source = None
        if threshold is None and calibration is None:
            calibration, source = _stored_calibration(database)
        self.spec, self.threshold, self.calibration = self._decision_rule(rule, rule_settings, threshold, calibration,
                                                                          source)
        self._owns_database = not isinstance(database, PlaceDatabase)
        self.database = self._database(database, method_options)
        try:
            self._load_places()
        except BaseException:
            self.close()
            raise
        self._session = uuid.uuid4().hex[:8]
        # per frame of this traverse: the places in the database before it was added (so frame
        # t searches places[:before[t - exclude_last]]), and its similarity row for sequences
        self._before: list[int] = []
        self._rows: deque[np.ndarray] = deque(maxlen=max(self.sequence_length - 1, 0) or None)
        self.decisions: list[FrameDecision] = []
        self.closures: list[Closure] = []

    # ------------------------------------------------------------------ setting up
    def _decision_rule(self, rule, rule_settings, threshold, calibration, source=None):
        if calibration is not None:
            if threshold is not None:
                raise ConfigError("give a threshold or a calibration file, not both (the calibration sets the "
                                  "threshold)")
            calibrated, source = _load_calibration(calibration, self.descriptor, self.sequence_length, source)
            spec = calibrated.spec
            if rule is not None or rule_settings:
                wanted = rule if isinstance(rule, AcceptanceSpec) else parse_acceptance(str(rule or spec.name),
                                                                                       rule_settings)
                if wanted.to_dict() != spec.to_dict():
                    raise ConfigError(f"{source}: calibrates rule {spec.name!r} with settings {spec.settings}, "
                                      f"but rule {wanted.name!r} with settings {wanted.settings} was asked for; "
                                      "its threshold means nothing for another rule")
            return spec, float(calibrated.threshold), calibrated
        if threshold is None:
            raise ConfigError("a loop closure needs an acceptance threshold: give one (--threshold T), a "
                              "calibration file (--calibration FILE, from `fdnet calibrate`), or a database "
                              "holding a calibration (`fdnet calibrate --db`)")
        # +inf accepts nothing: a run that only measures (e.g. to calibrate: calibrate_decisions)
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float, np.floating, np.integer)) \
                or math.isnan(float(threshold)) or float(threshold) == -math.inf:
            raise ConfigError(f"threshold must be a number (+inf accepts nothing), got {threshold!r}")
        if rule is None:
            raise ConfigError("name the acceptance rule (e.g. rule='margin'); `fdnet loop-closure --accept RULE`")
        spec = rule if isinstance(rule, AcceptanceSpec) else parse_acceptance(str(rule), rule_settings)
        return spec, float(threshold), None

    def _database(self, database, method_options):
        from fdnet.matching.database import MEMORY, PlaceDatabase

        if database is None:
            return PlaceDatabase.for_descriptor(self.descriptor, method_options=method_options)
        if isinstance(database, PlaceDatabase):
            database.check_descriptor(self.descriptor)
            return database
        path = Path(database)
        if str(database) != MEMORY and path.is_file() and path.stat().st_size > 0:
            return PlaceDatabase.open(path, descriptor=self.descriptor)
        return PlaceDatabase.create(path, self.descriptor, method_options=method_options)

    def _load_places(self) -> None:
        db = self.database
        self._names: list[str] = db.names
        self._known = set(self._names)
        self._vectors = _Vectors(db.dim, db.vectors)
        positions = db.positions
        self._positions: list | None = positions if all(p is not None for p in positions) else None
        times = [(m or {}).get("timestamp") for m in db.metadata]
        self._times: list | None = times if all(isinstance(t, (int, float)) for t in times) else None

    @property
    def places(self) -> int:
        """Places the detector searches over (the database's, including this traverse's frames)."""
        return len(self._vectors)

    @property
    def frames(self) -> int:
        """Frames of this traverse processed so far."""
        return len(self._before)

    # ------------------------------------------------------------------ one frame
    def describe(self, image) -> np.ndarray:
        """One frame's vector: ``image`` is a path or an (H, W, 3) array (uint8, or float in
        [0, 1]), brought to the descriptor's input size as ``fdnet`` loads every image."""
        from fdnet.data.images import load_image

        size = tuple(self.descriptor.input_size)
        if isinstance(image, (str, os.PathLike)):
            array = load_image(image, size)
        else:
            array = np.asarray(image)
            if array.ndim != 3 or array.shape[2] != 3:
                raise DataError(f"a frame must be an (H, W, 3) RGB image, got an array of shape {array.shape}")
            array = array.astype(np.float32) / 255.0 if array.dtype == np.uint8 else array.astype(np.float32)
            if array.shape[:2] != size:
                import cv2

                array = cv2.resize(array, (size[1], size[0]), interpolation=cv2.INTER_AREA)
        return np.asarray(self.descriptor.describe(array[None]), dtype=np.float32)[0]

    def process(self, image, timestamp: float | None = None, name: str | None = None,
                position: tuple[float, float] | None = None) -> Closure | None:
        """Describe the next frame, decide, add it to the database; the accepted closure or None.
        ``name`` (default: the path of ``image``, else a name unique to this run) is the place's
        name in the database; a rule that verifies geometry reads images by these names."""
        if name is None and isinstance(image, (str, os.PathLike)):
            name = str(Path(image).resolve())
        return self.process_vector(self.describe(image), timestamp=timestamp, name=name, position=position)

    def process_vector(self, vector: np.ndarray, timestamp: float | None = None, name: str | None = None,
                       position: tuple[float, float] | None = None) -> Closure | None:
        """:meth:`process` for a frame already described by the detector's descriptor."""
        v = np.asarray(vector, dtype=np.float32).reshape(-1)
        if v.shape[0] != self.database.dim:
            raise DataError(f"frame vector has {v.shape[0]} values, the {self.descriptor.name} places have "
                            f"{self.database.dim}")
        t = self.frames
        name = f"loop-closure-{self._session}/frame_{t:06d}" if name is None else str(name)
        if not np.isfinite(v).all():
            raise DataError(f"{name}: its {self.descriptor.name} vector is not finite (NaN or inf)")
        if name in self._known and not self.allow_duplicates:
            raise DataError(f"{self.database.path}: already holds a place named {name!r} (added in an earlier run?); "
                            "give each frame a new name, or allow duplicates")
        if timestamp is not None and (isinstance(timestamp, bool) or not isinstance(timestamp, (int, float))
                                      or not math.isfinite(timestamp)):
            raise DataError(f"{name}: timestamp must be a finite number of seconds, got {timestamp!r}")
        count = self.places
        # this traverse's last `exclude_last` frames are never candidates; places from earlier
        # sessions (and this traverse's older frames) are
        if self.exclude_last == 0 or t == 0:
            searchable = count
        else:  # frames t-N..t-1 excluded: the places there were before frame t-N was added
            searchable = self._before[max(t - self.exclude_last, 0)]
        if count:
            # One row against the map is a memory-bound matrix-vector product: BLAS threads only
            # add synchronisation, and on shared cores they made it ~5x slower (17 ms vs 3.7 ms
            # for 3000 x 2048 on the 2-core machine of docs/loop-closure.md).
            with _single_blas_thread():
                row = np.asarray(self.descriptor.similarity(v[None], self._vectors.view()), dtype=np.float32)[0]
        else:
            row = np.zeros(0, np.float32)
        if self.sequence_length > 1:
            from fdnet.matching.sequence import online_sequence_scores

            scores = online_sequence_scores([*self._rows, row], searchable)
        else:
            scores = row[:searchable]
        closure = None
        decision = FrameDecision(t, -1, float("nan"), False, int(searchable))
        if searchable > 0:
            match, score, similarity = self._decide(scores, name, timestamp, position)
            accepted = bool(score >= self.threshold)
            best = int(np.argmax(scores))
            decision = FrameDecision(t, match, score, accepted, int(searchable), best, float(scores[best]))
            if accepted:
                closure = Closure(t, name, match, self._names[match], score, similarity, self.spec.name,
                                  self.threshold, timestamp,
                                  None if self._times is None else float(self._times[match]))
        self._add(v, name, timestamp, position)
        self._before.append(count)
        if self.sequence_length > 1:
            self._rows.append(row)
        self.decisions.append(decision)
        if closure is not None:
            self.closures.append(closure)
        return closure

    def _decide(self, scores: np.ndarray, name: str, timestamp, position) -> tuple[int, float, float]:
        from fdnet.matching.similarity import top_k_of_matrix

        depth = min(self.spec.depth, len(scores))
        idx, top = top_k_of_matrix(scores[None], depth)
        needs_images = "images" in self.spec.needs
        if needs_images and not Path(name).is_file():
            raise ConfigError(f"rule {self.spec.name!r} verifies geometry on the images, but frame {name!r} is no "
                              "image file; process frames by path (or give name=PATH)")
        candidates = Candidates(
            retrieved=idx, scores=top, similarity_ceiling=float(getattr(self.descriptor, "similarity_ceiling", 1.0)),
            reference_times=None if self._times is None else np.asarray(self._times[:len(scores)], np.float64),
            reference_positions=None if self._positions is None else np.asarray(self._positions[:len(scores)]),
            query_paths=[Path(name)] if needs_images else None,
            reference_paths=self._names if needs_images else None,
            query_indices=np.array([self.frames]))
        decision = decide(self.spec, candidates)
        match = int(decision.match[0])
        similarity = float(scores[match])
        return match, float(decision.score[0]), similarity

    def _add(self, v: np.ndarray, name: str, timestamp, position) -> None:
        metadata = {"loop_closure_frame": self.frames, "session": self._session}
        if timestamp is not None:
            metadata["timestamp"] = float(timestamp)
        self._pending.append((v, name, position, metadata))
        self._vectors.append(v)
        self._names.append(name)
        self._known.add(name)
        if self._positions is not None:
            if position is None:
                self._positions = None
            else:
                self._positions.append(tuple(float(c) for c in position))
        if self._times is not None:
            if timestamp is None:
                self._times = None
            else:
                self._times.append(float(timestamp))
        if len(self._pending) >= self.commit_every:
            self.flush()

    def flush(self) -> None:
        """Store the frames not stored yet, in one transaction."""
        if not self._pending:
            return
        vectors, names, positions, metadata = zip(*self._pending)
        result = self.database.add(np.stack(vectors), list(names),
                                   None if all(p is None for p in positions) else list(positions),
                                   metadata=list(metadata), allow_duplicates=self.allow_duplicates)
        self._pending = []
        if result.added != len(names):
            raise DataError(f"{self.database.path}: already holds place(s) named {', '.join(result.skipped[:3])} "
                            "(added by another process?); they were not added again")
        if result.places != self.places:
            # Another process added places since we last looked: reload, so place indices stay
            # the database's (rare; the whole map is read again).
            self._load_places()

    def close(self) -> None:
        """Store the frames not stored yet; close the database if the detector opened it."""
        try:
            if getattr(self, "_pending", None) and getattr(self, "database", None) is not None:
                self.flush()
        finally:
            if self._owns_database and getattr(self, "database", None) is not None:
                self.database.close()
                self.database = None

    def __enter__(self) -> "LoopClosureDetector":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---------------------------------------------------------------------- events on disk
class EventLog:
    """Accepted closures written as they happen: a CSV (header :data:`EVENT_COLUMNS`) and,
    optionally, JSON lines with the same keys.

    Guarantee: both files are created fresh when the log opens (the header written atomically,
    :func:`fdnet.io.atomic_write_text`); when :meth:`write` returns, the event's line is on disk
    in each file (the whole line in one ``os.write`` on an ``O_APPEND`` descriptor, then
    ``fsync``). A crash or ``kill -9`` therefore leaves every event reported before it, each line
    complete; only a power cut in the middle of a write can leave one incomplete last line (no
    final newline), which readers drop. One fsync per accepted closure, not per frame.
    """

    def __init__(self, csv_path: str | os.PathLike, jsonl_path: str | os.PathLike | None = None):
        from fdnet.io import atomic_write_text

        self.paths = [Path(csv_path)] + ([Path(jsonl_path)] if jsonl_path is not None else [])
        if len({p.resolve() for p in self.paths}) != len(self.paths):
            raise ConfigError(f"{csv_path}: the CSV and the JSON-lines events must be two different files")
        self._fds: list[int] = []
        atomic_write_text(self.paths[0], self._csv_line(EVENT_COLUMNS))
        if jsonl_path is not None:
            atomic_write_text(self.paths[1], "")
        try:
            for path in self.paths:
                self._fds.append(os.open(path, os.O_WRONLY | os.O_APPEND))
        except OSError as exc:
            self.close()
            raise DataError(f"cannot open the events file for appending ({exc.strerror or exc})") from None
        self.count = 0

    @staticmethod
    def _csv_line(values) -> str:
        buffer = io.StringIO()
        csv.writer(buffer, lineterminator="\n").writerow(values)
        return buffer.getvalue()

    def write(self, closure: Closure) -> None:
        event = closure.to_dict()
        cells = ["" if event[c] is None else (f"{event[c]:.6f}" if isinstance(event[c], float) else
                                              spreadsheet_text(event[c]) if c in ("query", "match") else event[c])
                 for c in EVENT_COLUMNS]
        lines = [self._csv_line(cells)]
        if len(self._fds) > 1:
            lines.append(json.dumps({c: event[c] for c in EVENT_COLUMNS}, allow_nan=False) + "\n")
        for fd, line, path in zip(self._fds, lines, self.paths):
            data = line.encode("utf-8", "surrogateescape")  # a name that is not UTF-8: its own bytes
            try:
                written = os.write(fd, data)
                if written != len(data):  # only a full disk stops a regular file's write short
                    raise OSError(f"wrote {written} of {len(data)} bytes")
                os.fsync(fd)
            except OSError as exc:
                raise DataError(f"{path}: cannot write the loop-closure event ({getattr(exc, 'strerror', None) or exc})"
                                ) from None
        self.count += 1

    def close(self) -> None:
        while self._fds:
            os.close(self._fds.pop())

    def __enter__(self) -> "EventLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---------------------------------------------------------------------- evaluation
def _evaluable(decisions: Sequence[FrameDecision], ground_truth):
    """(the frames that had a place to search, their ground truth cut to those places)."""
    from fdnet.data.groundtruth import GroundTruth

    if ground_truth.num_queries != len(decisions):
        raise DataError(f"the ground truth has {ground_truth.num_queries} queries but the traverse has "
                        f"{len(decisions)} frames")
    evaluated = [d for d in decisions if d.match >= 0]
    if not evaluated:
        raise DataError("no frame had a place to search (exclude-last covers the whole traverse): nothing to evaluate")
    positives = [ground_truth.positives[d.query_index] for d in evaluated]
    positives = [p[p < d.searchable] for p, d in zip(positives, evaluated)]
    truth = GroundTruth(positives, ground_truth.num_references,
                        f"{ground_truth.description}; true matches cut to each frame's searchable places")
    if not truth.has_match.any():
        raise DataError(f"no frame revisits a place it could search ({ground_truth.description}; frames after "
                        "exclude-last): nothing to evaluate. Does the traverse return to a place it saw before?")
    return evaluated, truth


def evaluate_decisions(decisions: Sequence[FrameDecision], ground_truth, threshold: float, rule: str) -> dict:
    """Every frame's decision against ``ground_truth`` (queries = this traverse's frames in
    order, references = the database's places by index), with the metrics of
    :func:`fdnet.evaluation.metrics.evaluate_retrieval` over each frame's acceptance score and
    the place it vouches for (recall over queries: R@100P, R@99P, R@95P, P@maxR, AUC-PR,
    Recall@1), and the operating point at ``threshold`` (what the run accepted).

    A frame can only close a loop with a place it was allowed to search, so each frame's true
    matches are cut to the places searchable for it (its own last frames are no revisit); frames
    with nothing to search are left out (they can neither find nor miss anything).
    """
    from fdnet.evaluation.metrics import RECALL_OVER_QUERIES, evaluate_retrieval

    evaluated, truth = _evaluable(decisions, ground_truth)
    score = np.array([d.score for d in evaluated], dtype=np.float64)
    match = np.array([d.match for d in evaluated], dtype=np.int64)
    metrics = evaluate_retrieval(np.array([[d.best] for d in evaluated]),
                                 np.array([[d.best_similarity] for d in evaluated]), truth,
                                 protocol=RECALL_OVER_QUERIES, ns=(1,), acceptance_scores=score,
                                 accepted_matches=match, acceptance=rule)
    accepted = score >= float(threshold)
    correct = truth.correct_mask(match[:, None])[:, 0]
    true_closures = int((accepted & correct).sum())
    revisits = int(truth.has_match.sum())
    return {
        "frames": len(decisions),
        "frames_evaluated": len(evaluated),
        "frames_with_revisit": revisits,
        "ground_truth": truth.description,
        "metrics": metrics.to_dict(include_curve=False),
        "at_threshold": {
            "threshold": float(threshold),
            "accepted": int(accepted.sum()),
            "true": true_closures,
            "false": int(accepted.sum()) - true_closures,
            "precision": true_closures / int(accepted.sum()) if accepted.any() else 1.0,
            "recall": true_closures / revisits,
        },
    }


def calibrate_decisions(decisions: Sequence[FrameDecision], ground_truth, detector: "LoopClosureDetector",
                        target_precision: float, measured_on: dict | None = None):
    """A :class:`~fdnet.decisions.calibration.Calibration` of ``detector``'s rule from one
    traverse with ground truth: the threshold on its frames' acceptance scores that reaches
    ``target_precision`` with the largest recall
    (:func:`fdnet.decisions.calibration.choose_threshold`), over the same frames and true
    matches as :func:`evaluate_decisions`. Calibrating on the robot's own kind of traverse
    matters: a cross-condition pair has none of the look-alike places a traverse meets in its
    own recent past (docs/loop-closure.md)."""
    from datetime import datetime, timezone

    from fdnet import __version__
    from fdnet.decisions.calibration import Calibration, check_target, choose_threshold

    target = check_target(target_precision)
    evaluated, truth = _evaluable(decisions, ground_truth)
    score = np.array([d.score for d in evaluated], dtype=np.float64)
    match = np.array([d.match for d in evaluated], dtype=np.int64)
    correct = truth.correct_mask(match[:, None])[:, 0]
    chosen = choose_threshold(score, correct, truth.has_match, target)
    notes = []
    if not math.isfinite(chosen.threshold):
        notes.append(f"no threshold reaches precision {target:g} on this traverse (its most confident frame is "
                     "already wrong): nothing will be accepted")
    length = detector.sequence_length if detector.sequence_length > 1 else 0
    where = {"loop_closure": True, "ground_truth": truth.description, "exclude_last": detector.exclude_last,
             "frames": len(decisions), "frames_evaluated": len(evaluated), "sequence_length": length,
             **(measured_on or {})}
    return Calibration(
        rule=detector.spec.name, settings=detector.spec.settings, threshold=chosen.threshold,
        target_precision=target, precision=chosen.precision, recall=chosen.recall, accepted=chosen.accepted,
        num_queries=len(evaluated), method=detector.descriptor.name, fingerprint=detector.descriptor.fingerprint(),
        sequence_length=length, measured_on=where,
        created=datetime.now(timezone.utc).isoformat(timespec="seconds"), fdnet_version=__version__, notes=notes)


# ---------------------------------------------------------------------- a traverse from a folder
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
    evaluation: dict | None = None
    calibration: str | None = None
    #: the calibration this run wrote (``calibrate_to``): path, threshold, precision, recall
    calibrated: dict | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("nan")

    def to_dict(self) -> dict:
        out = asdict(self)
        out["frames_per_second"] = self.frames_per_second
        return out


def run_traverse(images: str | os.PathLike, descriptor, database=None, *, exclude_last: int,
                 events_csv: str | os.PathLike, events_jsonl: str | os.PathLike | None = None,
                 rule: str | None = None, rule_settings=None, threshold: float | None = None, calibration=None,
                 sequence_length: int = 1, ground_truth: str | os.PathLike | None = None,
                 calibrate_to: str | os.PathLike | None = None, target_precision: float = 1.0,
                 method_options: dict | None = None, commit_every: int = 1, batch_size: int = 16,
                 workers: int | None = None, progress: bool = False,
                 log: Callable[[str], None] | None = None) -> TraverseReport:
    """Run a :class:`LoopClosureDetector` over the images of one folder (or video or ROS bag: its
    frames bring their timestamps, and a bag's its positions, for ``radius_s`` / ``radius_m``; one
    traverse, in fdnet's one image order), writing each accepted closure to ``events_csv`` (and
    ``events_jsonl``) as it is accepted (:class:`EventLog`). ``database``: a place-database file
    from earlier sessions (or a new file to create; None = in memory only). ``ground_truth``: a
    CSV of :class:`~fdnet.data.groundtruth.GroundTruth` (``fdnet groundtruth`` from positions,
    or a frame list ``query_index,reference_indices``) whose queries are the frames and whose
    references are the database's places (for a new database: the same frames); the run is
    then evaluated (:func:`evaluate_decisions`). ``commit_every``: frames per database
    transaction (see :class:`LoopClosureDetector`). ``calibrate_to``: also choose the threshold
    that reaches ``target_precision`` on this traverse (:func:`calibrate_decisions`, needs
    ``ground_truth``) and write that calibration there (YAML); without a threshold or
    calibration such a run accepts nothing (threshold +inf). Frames are described ``batch_size`` at a time
    (each vector depends only on its own image, so this changes no decision) with a progress bar
    in frames/s when ``progress``. Every refusal (paths, rule, calibration, ground truth,
    database) comes before the first frame is described.
    """
    from fdnet.data.groundtruth import GroundTruth
    from fdnet.data.images import list_images
    from fdnet.data.sources import frame_records, positions_in_metres
    from fdnet.io import ensure_writable
    from fdnet.matching.database import check_place_names

    say = log or (lambda message: None)
    if calibrate_to is not None:
        from fdnet.decisions.calibration import check_target

        if ground_truth is None:
            raise ConfigError("calibrating on a traverse needs its ground truth (--ground-truth CSV)")
        check_target(target_precision)
        ensure_writable(calibrate_to, what="calibration file")
        if threshold is None and calibration is None:
            threshold = math.inf
    ensure_writable(events_csv, what="events CSV")
    if events_jsonl is not None:
        ensure_writable(events_jsonl, what="events JSON lines")
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise ConfigError(f"batch size must be a whole number of at least 1, got {batch_size!r}")
    paths = list_images(images)
    names = [str(p.resolve()) for p in paths]
    check_place_names(names)  # before any frame is described: the database could not store them
    # frames of a video or bag carry their time, and a bag's its position: radius_s / radius_m use them
    records = frame_records(paths)
    times = [r.timestamp for r in records]
    positions = positions_in_metres(records)
    with LoopClosureDetector(descriptor, database, exclude_last=exclude_last, rule=rule,
                             rule_settings=rule_settings, threshold=threshold, calibration=calibration,
                             sequence_length=sequence_length, method_options=method_options,
                             commit_every=commit_every) as detector:
        db = detector.database
        already = db.existing_names(names)
        if already:
            first = next(n for n in names if n in already)
            raise DataError(f"{db.path}: already holds {len(already)} of these {len(names)} frames (e.g. {first}); "
                            "a traverse is added once: use a copy of the database from before that run, or "
                            "another database")
        places_before = detector.places
        truth = None
        if ground_truth is not None:
            truth = GroundTruth.from_csv(ground_truth, num_references=places_before + len(paths),
                                         num_queries=len(paths))
            truth.check_names(paths, [*detector._names, *paths])
        # a rule that looks at the images (verification) refuses unusable ones (too small for
        # local features) before the first frame is described
        detector.spec.check_images(paths, [*detector._names, *names])
        say(f"loop closure over {len(paths)} frames of {images} with {descriptor.name}, rule {detector.spec.name} "
            f"(threshold {detector.threshold:g}), {places_before} places in {db.path} before the run")
        t0 = time.perf_counter()
        events = _detect_over(detector, descriptor, paths, names, times, positions, events_csv, events_jsonl,
                              batch_size, workers, progress)
        detector.flush()
        seconds = time.perf_counter() - t0
        report = TraverseReport(
            frames=detector.frames, closures=len(detector.closures), seconds=seconds, places_before=places_before,
            places_after=detector.places, rule=detector.spec.name, rule_settings=detector.spec.settings,
            threshold=detector.threshold,
            sequence_length=detector.sequence_length, exclude_last=detector.exclude_last, database=str(db.path),
            events=[str(p) for p in events.paths],
            calibration=None if calibration is None else str(calibration))
        if truth is not None:
            report.evaluation = evaluate_decisions(detector.decisions, truth, detector.threshold, detector.spec.name)
        if calibrate_to is not None:
            report.calibrated = _calibrate_on_traverse(detector, truth, target_precision, images, ground_truth,
                                                       calibrate_to)
    return report


def _detect_over(detector: LoopClosureDetector, descriptor, paths, names, times, positions, events_csv,
                 events_jsonl, batch_size: int, workers: int | None, progress: bool) -> EventLog:
    """Describe ``paths`` ``batch_size`` at a time and feed each vector to ``detector``, writing
    each accepted closure to the event log as it is accepted; returns the (closed) log."""
    from fdnet.descriptors.pipeline import describe_stream

    bar = None
    if progress:
        from fdnet.progress import progress_bar

        bar = progress_bar(total=len(paths), desc=f"loop closure [{descriptor.name}]", unit="frame",
                           smoothing=0.1)
    try:
        with EventLog(events_csv, events_jsonl) as events:
            for start, vectors in describe_stream(descriptor, paths, batch_size, workers=workers):
                for offset, vector in enumerate(np.asarray(vectors, dtype=np.float32)):
                    k = start + offset
                    closure = detector.process_vector(vector, name=names[k], timestamp=times[k],
                                                      position=positions[k])
                    if closure is not None:
                        events.write(closure)
                if bar is not None:
                    bar.update(len(vectors))
                    bar.set_postfix(closures=events.count, refresh=False)
    finally:
        if bar is not None:
            bar.close()
    return events


def _calibrate_on_traverse(detector: LoopClosureDetector, truth, target_precision: float, images,
                           ground_truth, calibrate_to) -> dict:
    """Choose the threshold reaching ``target_precision`` on this traverse's decisions, write it
    to ``calibrate_to`` and return what :attr:`TraverseReport.calibrated` records."""
    from fdnet.decisions.calibration import save_calibration

    calibrated = calibrate_decisions(detector.decisions, truth, detector, target_precision,
                                     {"images": str(Path(images).resolve()),
                                      "ground_truth_file": str(Path(ground_truth).resolve())})
    written = save_calibration(calibrated, calibrate_to)
    return {"path": str(written), "threshold": calibrated.threshold,
            "target_precision": calibrated.target_precision,
            "precision": calibrated.precision, "recall": calibrated.recall,
            "notes": list(calibrated.notes)}
