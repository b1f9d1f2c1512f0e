"""Online loop closure: a robot's traverse, frame by frame, against a persistent place database.

For each new frame, :class:`LoopClosureDetector`:

1. describes it (or takes its vector);
2. scores it against the places in the database *except the robot's recent past*, found from the
   traverse itself (:mod:`fdnet.decisions.loop_recency`) with the gates of
   :mod:`fdnet.decisions.loop_gates`: single images, or with ``sequence_length`` > 1 the SeqSLAM
   sequence similarity over the robot's last frames, never across a seam between recordings;
3. turns the candidates into one acceptance score with a rule of :mod:`fdnet.decisions.acceptance`;
4. accepts the best candidate when that score reaches the threshold (given, or from a calibration
   made for the same model, :mod:`fdnet.decisions.loop_trust`), with its ``p_correct``;
5. adds the frame to the database (one transaction) and returns the :class:`Closure`, or None.

**Causal.** Every number a frame's decision uses comes from that frame and frames processed
before it, and nothing is revised later: the events up to frame t do not depend on frames after t.
The detector keeps the database's vectors in memory (read once, then appended), or, once the
database keeps them in its vector file (its ``compressed_from`` places,
:mod:`fdnet.matching.database.vector_store`), reads the rows it needs from there; which places a
frame may match and how each scores (every place, or through an index on large maps) is its
search, :mod:`fdnet.decisions.loop_candidates`; the detector itself is gates, rule and
consistency over those candidates, and the storage of each frame.
:func:`fdnet.decisions.loop_traverse.run_traverse` is what ``fdnet loop-closure`` runs.
"""

from __future__ import annotations

import logging
import math
import os
import uuid
from pathlib import Path

import numpy as np

from fdnet.decisions.acceptance import Candidates, decide
from fdnet.decisions.calibration import stored_calibration
from fdnet.decisions.loop_candidates import FrameQuery, LoopCandidates, SearchPlan
from fdnet.decisions.loop_gates import (  # noqa: F401
    ConsistencyGate,
    FrameSignals,
    LoopGates,
    RecentPast,
    frame_signals,
    informative_frames,
    is_still,
)
from fdnet.decisions.loop_recency import GapDetector, Seams
from fdnet.decisions.loop_records import EVENT_COLUMNS, Closure, FrameDecision  # noqa: F401
from fdnet.decisions.loop_settings import SEARCH_KINDS, LoopClosureSettings  # noqa: F401
from fdnet.decisions.loop_threads import FrameThreads
from fdnet.decisions.loop_trust import (  # noqa: F401
    LOOP_CALIBRATION_FILE,
    DriftCheck,
    calibrated_gates,
    decision_rule,
    resolve_calibration,
)
from fdnet.errors import ConfigError, DataError
from fdnet.matching.database.storage import place_name
from fdnet.matching.file_rows import FileRows
from fdnet.matching.place_map import OptionalFloats

logger = logging.getLogger(__name__)


class LoopClosureDetector:
    """Online loop-closure detection over a place database (see the module docstring).

    ``descriptor``: a :mod:`fdnet.descriptors` method. ``database``: a
    :class:`~fdnet.matching.database.PlaceDatabase` (e.g. from earlier sessions), a path (opened
    when the file exists, else created), or None (a scratch database in memory); its vectors
    must come from ``descriptor`` (same fingerprint). ``settings``: a
    :class:`~fdnet.decisions.loop_settings.LoopClosureSettings` (rule, threshold or calibration,
    sequence length, gates, search, storage), with any of its fields given as keywords on top
    (``LoopClosureDetector(d, db, sequence_length=10, calibration="runs/nordland")``). Without
    threshold and calibration, the calibration stored in the database (``fdnet calibrate
    --db``) is used. ``commit_every`` > 1 stores frames N at a time (the rest at
    :meth:`flush`/:meth:`close`), which changes no decision (the
    detector searches its own copy of the vectors) but a crash loses up to N - 1 frames.
    """

    def __init__(self, descriptor, database=None, settings: LoopClosureSettings | None = None, **options):
        from fdnet.matching.database import PlaceDatabase

        settings = (settings or LoopClosureSettings()).with_options(**options)
        source = None
        threshold, calibration = settings.threshold, settings.calibration
        if threshold is None and calibration is None:
            calibration, source = stored_calibration(database)
        calibration, source = resolve_calibration(calibration, source)
        sequence_length = settings.sequence_length
        if sequence_length is None:  # a calibration's own, else single images
            sequence_length = int(calibration.sequence_length) if calibration is not None else 1
        if descriptor.needs_fit:
            raise ConfigError(
                f"method {descriptor.name!r} must be given what it learns from (--fit DIR, or dbow's "
                "--vocabulary) before it can describe frames online"
            )
        self.descriptor = descriptor
        self.settings = settings
        self.exclude_last = settings.exclude_last
        self.sequence_length = int(sequence_length)
        # neutral values that pad the start of each similarity row with sequences: the first place
        # that can end a full-length sequence at every velocity (0 for single images)
        from fdnet.matching.sequence import sequence_reach

        self._first_full = sequence_reach(self.sequence_length)
        self.allow_duplicates = settings.allow_duplicates
        self.commit_every = settings.commit_every
        self._frame_threads = FrameThreads(settings.frame_threads)
        from fdnet.decisions.loop_search import INDEX_FROM

        self.search = settings.search
        self.index_from = INDEX_FROM if settings.index_from is None else settings.index_from
        # frames decided but not yet stored (commit_every > 1): vectors, names, positions, metadata
        self._pending: list[tuple] = []
        self._calibration_source = source or "the calibration"
        self.spec, self.threshold, self.calibration = decision_rule(
            descriptor, self.sequence_length, settings.rule, settings.rule_settings, threshold, calibration, source
        )
        self.gates = calibrated_gates(self.calibration, settings.gates, source)
        self._owns_database = not isinstance(database, PlaceDatabase)
        self.database = self._database(database, settings.method_options)
        try:
            self._load_places()
        except BaseException:
            self.close()
            raise
        self._session = uuid.uuid4().hex[:8]
        self._upcoming = np.zeros((0, self.database.dim), np.float32)  # the next frames' vectors (look_ahead)
        self._start_traverse()

    def _start_traverse(self) -> None:
        # the search's state over this traverse: per frame, the places before it, its recent past,
        # its similarity row for sequences (:mod:`fdnet.decisions.loop_candidates`)
        self.candidates = LoopCandidates(
            SearchPlan(
                self.descriptor.similarity,
                self.sequence_length,
                self._first_full,
                self.spec.depth,
                self.gates,
                self.exclude_last,
            )
        )
        #: the rule scores under the threshold, checked against the calibration's
        self._drift = DriftCheck(self.calibration, self._calibration_source)
        self._consistency = ConsistencyGate(self.gates.consistency, self.gates.consistency_window)
        self._gaps = GapDetector()
        self._last_thumbnail: np.ndarray | None = None
        self.decisions: list[FrameDecision] = []
        self.closures: list[Closure] = []
        self._gated = {"uninformative": 0, "still_frames": 0, "held_by_consistency": 0}

    @property
    def gate_counts(self) -> dict:
        """What the gates did so far: frames that were uninformative, frames taken while still,
        frames whose exclusion reached further back than exclude_last (a still robot),
        candidates the consistency gate held back (score at the threshold, matches not yet
        consistent)."""
        return {
            "uninformative": self._gated["uninformative"],
            "still_frames": self._gated["still_frames"],
            "still_exclusion": self.candidates.still_exclusions,
            "held_by_consistency": self._gated["held_by_consistency"],
        }

    @property
    def excluded_back(self) -> list[int]:
        """Per frame of this traverse: how many frames back its exclusion went."""
        return self.candidates.excluded_back

    # ------------------------------------------------------------------ setting up
    def _database(self, database, method_options):
        from fdnet.matching.database import PlaceDatabase, holds_a_database

        if database is None:
            return PlaceDatabase.for_descriptor(self.descriptor, method_options=method_options)
        if isinstance(database, PlaceDatabase):
            database.check_descriptor(self.descriptor)
            return database
        path = Path(database)
        if holds_a_database(path):
            return PlaceDatabase.open(path, descriptor=self.descriptor)
        # a new file, or what a failed create left (empty, or SQLite without tables): created there;
        # compressed_from also sets from what size it keeps its vectors in a file
        from fdnet.matching.index import IndexSettings

        compressed_from = self.settings.compressed_from
        index = None if compressed_from is None else IndexSettings(compressed_from=compressed_from)
        return PlaceDatabase.create(path, self.descriptor, index=index, method_options=method_options)

    def _load_places(self) -> None:
        db = self.database
        self.map = db.place_map(vectors=True)
        self.map.keep_loop_columns_only()
        # times and positions are used (radius_s, radius_m, the events' columns) only while every
        # place has them
        self._has_times = self.map.loop_column("timestamp").all_present()
        self._has_positions = self.map.positions.all_present()
        # an earlier session, or a segment an earlier run marked, starts a new segment of the map
        self._seams = Seams(self._first_full)
        previous = None
        for start, session in zip(self.map.loop_column("segment_start").view(), self.map.loop_column("session")):
            self._seams.add(start or session != previous)
            previous = session

    @property
    def _times(self) -> OptionalFloats | None:
        return self.map.loop_column("timestamp") if self._has_times else None

    @property
    def _positions(self) -> OptionalFloats | None:
        return self.map.positions if self._has_positions else None

    @property
    def _informative(self):
        return self.map.loop_column("informative")

    @property
    def places(self) -> int:
        """Places the detector searches over (the database's, including this traverse's frames)."""
        return len(self.map)

    @property
    def drift(self) -> dict | None:
        """How this run's rejected scores departed from its calibration's (None: they did not)."""
        return self._drift.drift

    @property
    def segments(self) -> int:
        """Segments of the map (recordings driven without a break, :mod:`fdnet.decisions.loop_recency`)."""
        return self._seams.segments

    @property
    def frame_threads(self) -> FrameThreads:
        """The torch threads frames are described on (``used``: frames per count)."""
        return self._frame_threads

    @property
    def frames(self) -> int:
        """Frames of this traverse processed so far."""
        return len(self.candidates.before)

    # ------------------------------------------------------------------ one frame
    def load(self, image) -> np.ndarray:
        """One frame as the descriptor gets it: ``image`` is a path or an (H, W, 3) RGB array
        (uint8 0..255, or float in [0, 1]; a float array outside [0, 1] is refused, its scale
        being unknown), brought to the descriptor's input size exactly as a file of the same
        pixels would be (:func:`fdnet.data.images.resize_array`); (H, W, 3) float32 in [0, 1]."""
        from fdnet.data.images import load_image, resize_array

        size = tuple(self.descriptor.input_size)
        if isinstance(image, (str, os.PathLike)):
            return load_image(image, size)
        return resize_array(image, size)

    def describe(self, image) -> np.ndarray:
        """One frame's vector (``image`` as for :meth:`load`)."""
        return self._vector(image, self.load(image))

    def _vector(self, image, array: np.ndarray) -> np.ndarray:
        # a descriptor of vectors computed elsewhere finds them by the frame's path
        paths = [image] if isinstance(image, (str, os.PathLike)) else []
        with self.descriptor.images_of(paths):
            vector = self._frame_threads.run(lambda: self.descriptor.describe(array[None]))
        return np.asarray(vector, dtype=np.float32)[0]

    def process(
        self,
        image,
        timestamp: float | None = None,
        name: str | None = None,
        position: tuple[float, float] | None = None,
        new_segment: bool = False,
    ) -> Closure | None:
        """Describe the next frame, decide, add it to the database; the accepted closure or None.
        ``image``: a path or an (H, W, 3) RGB array (see :meth:`load`). ``name`` (default: the
        path of ``image``, else a name unique to this run) is the place's name in the database;
        a rule that verifies geometry reads images by these names."""
        if name is None and isinstance(image, (str, os.PathLike)):
            name = place_name(image)
        array = self.load(image)
        vector = self._vector(image, array)
        return self.process_vector(
            vector,
            timestamp=timestamp,
            name=name,
            position=position,
            signals=frame_signals(array[None]),
            new_segment=new_segment,
        )

    def process_vector(
        self,
        vector: np.ndarray,
        timestamp: float | None = None,
        name: str | None = None,
        position: tuple[float, float] | None = None,
        signals: FrameSignals | None = None,
        new_segment: bool = False,
        _replay: dict | None = None,
    ) -> Closure | None:
        """:meth:`process` for a frame already described by the detector's descriptor.
        ``signals``: the frame's :class:`~fdnet.decisions.loop_gates.FrameSignals` (from its
        pixels) for the uninformative-frame and still-robot gates; without them those gates
        cannot see the frame and let it through. ``new_segment``: the frame starts a new
        recording (a new pass of the route, after a break): no sequence spans the seam
        (:mod:`fdnet.decisions.loop_recency`); a gap in the timestamps starts one too."""
        t = self.frames
        v, name = self._checked_frame(vector, name, timestamp)
        count = self.places
        gap = self._gaps.gap(None if timestamp is None else float(timestamp))
        if _replay is not None:  # resume(): what the interrupted run stored for this frame
            informative, still = _replay["informative"], _replay["still"]
            new_segment = _replay["segment_start"]
        else:
            informative, still = True, False
            if signals is not None:
                informative = bool(informative_frames(signals.statistics[:1], self.gates)[0])
                still = t > 0 and is_still(signals.thumbnails[0], self._last_thumbnail, self.gates)
                self._last_thumbnail = signals.thumbnails[0]
        new_segment = bool(new_segment) or gap or t == 0
        if new_segment:
            self.candidates.new_segment(t)
        # a map whose vectors are in the database's vector file is searched through compressed codes
        in_file = isinstance(self.map.vectors, FileRows)
        if (
            self.candidates.indexed is None
            and self.search != "exact"
            and (self.search == "index" or count >= self.index_from or in_file)
        ):
            self.candidates.use_index(self.database.dim, 0 if in_file else self.settings.compressed_from)
            # codes over the database's places come from (and go to) its codes cache: a run over a
            # large database does not train them again (a minute at 10^6 places, 15 at 10^7)
            self.candidates.indexed.codes_source = self.database.codes_cache
        if self.candidates.indexed is not None:
            self.candidates.indexed.look_ahead(self._upcoming)
        self._upcoming = self._upcoming[:0]
        frame = FrameQuery(v, t, count, informative, still, timestamp, position)
        ids, scores, searchable = self.candidates.candidates(frame, self.map, self._seams)
        decision, closure = self._judge(frame, name, ids, scores, searchable)
        self._add(v, name, timestamp, position, informative, still, new_segment, store=_replay is None)
        self.candidates.frame_done(count)
        self.decisions.append(decision)
        if closure is not None:
            self.closures.append(closure)
        return closure

    def look_ahead(self, vectors) -> None:
        """The vectors of the frames :meth:`process_vector` will get next, in order (a batch
        already described): on a map searched through compressed codes their neighbours are
        found in one call with the next frame's. The decisions are the same without it."""
        upcoming = np.asarray(vectors, dtype=np.float32)
        if upcoming.size and (upcoming.ndim != 2 or upcoming.shape[1] != self.database.dim):
            raise DataError(
                f"look_ahead: expected (frames, {self.database.dim}) vectors of the {self.descriptor.name} places, "
                f"got an array of shape {upcoming.shape}"
            )
        self._upcoming = upcoming.reshape(-1, self.database.dim)

    def _checked_frame(self, vector, name: str | None, timestamp) -> tuple[np.ndarray, str]:
        """The frame's vector as float32 and its place name, or a DataError saying what is wrong."""
        v = np.asarray(vector, dtype=np.float32).reshape(-1)
        if v.shape[0] != self.database.dim:
            raise DataError(
                f"frame vector has {v.shape[0]} values, the {self.descriptor.name} places have " f"{self.database.dim}"
            )
        name = f"loop-closure-{self._session}/frame_{self.frames:06d}" if name is None else str(name)
        if not np.isfinite(v).all():
            raise DataError(f"{name}: its {self.descriptor.name} vector is not finite (NaN or inf)")
        if not self.allow_duplicates and name in self.map:
            raise DataError(
                f"{self.database.path}: already holds a place named {name!r} (added in an earlier run?); "
                "give each frame a new name, or allow duplicates"
            )
        if timestamp is not None and (
            isinstance(timestamp, bool) or not isinstance(timestamp, (int, float)) or not math.isfinite(timestamp)
        ):
            raise DataError(f"{name}: timestamp must be a finite number of seconds, got {timestamp!r}")
        return v, name

    def _judge(
        self, frame: FrameQuery, name: str, ids: np.ndarray, scores: np.ndarray, searchable: int
    ) -> tuple[FrameDecision, Closure | None]:
        """The gates, the rule and the consistency gate over the frame's candidates: its
        decision, and the closure when accepted."""
        t = frame.t
        if searchable <= 0:
            self._gated["uninformative"] += not frame.informative
            return FrameDecision(t, -1, float("nan"), False, int(searchable)), None
        gated = "" if frame.informative else "uninformative"
        if not gated and frame.still and not self.gates.decide_when_still:
            gated = "still"
        if not gated and t - self.candidates.segment_first + 1 < self.sequence_length:
            gated = "incomplete sequence"
        if not gated and (not len(ids) or not self._informative.view(searchable).any()):
            gated = "no informative place"
        best = int(ids[0]) if len(ids) else -1
        best_similarity = float(scores[0]) if len(ids) else self._floor
        if gated:
            self._gated["uninformative"] += not frame.informative
            self._gated["still_frames"] += gated == "still"
            self._consistency.update(-1, -math.inf)
            return FrameDecision(t, -1, -math.inf, False, int(searchable), best, best_similarity, gated=gated), None
        match, rule_score, similarity = self._decide(ids, scores, name, searchable)
        score = self._consistency.update(match, rule_score)
        accepted = bool(score >= self.threshold)
        if rule_score >= self.threshold and not accepted:
            self._gated["held_by_consistency"] += 1
        decision = FrameDecision(
            t, match, score, accepted, int(searchable), best, best_similarity, rule_score=rule_score
        )
        if math.isfinite(rule_score) and rule_score < self.threshold:
            self._drift.add(rule_score)
        if not accepted:
            return decision, None
        position = frame.position
        here = (None, None) if position is None else tuple(float(c) for c in list(position)[:2])
        there = (None, None) if self._positions is None else tuple(self._positions[match][:2])
        closure = Closure(
            t,
            name,
            match,
            self.map.names[match],
            score,
            similarity,
            self.spec.name,
            self.threshold,
            frame.timestamp,
            None if self._times is None else float(self._times[match]),
            *here,
            *there,
            self._p_correct(score),
        )
        return decision, closure

    def _p_correct(self, score: float) -> float | None:
        p = float(self.calibration.p_correct([score])[0]) if self.calibration is not None else math.nan
        return p if math.isfinite(p) else None

    #: best-match similarity recorded for a frame whose search found no candidate
    _floor = -1.0

    def _decide(self, ids: np.ndarray, scores: np.ndarray, name: str, searchable: int) -> tuple[int, float, float]:
        """The rule over the frame's candidates (place ids best first, their scores): (the place
        it vouches for, its acceptance score, that place's similarity)."""
        needs_images = "images" in self.spec.needs
        if needs_images and not Path(name).is_file():
            raise ConfigError(
                f"rule {self.spec.name!r} verifies geometry on the images, but frame {name!r} is no "
                "image file; process frames by path (or give name=PATH)"
            )
        candidates = Candidates(
            retrieved=np.asarray(ids, np.int64)[None],
            scores=np.asarray(scores, np.float64)[None],
            similarity_ceiling=float(self.descriptor.similarity_ceiling),
            reference_times=None if self._times is None else self._times.array(searchable),
            reference_positions=None if self._positions is None else self._positions.array(searchable),
            query_paths=[Path(name)] if needs_images else None,
            reference_paths=self.map.names if needs_images else None,
            query_indices=np.array([self.frames]),
        )
        decision = decide(self.spec, candidates)
        match = int(decision.match[0])
        similarity = float(np.asarray(scores)[np.flatnonzero(np.asarray(ids) == match)[0]])
        return match, float(decision.score[0]), similarity

    def _add(
        self,
        v: np.ndarray,
        name: str,
        timestamp,
        position,
        informative: bool = True,
        still: bool = False,
        new_segment: bool = False,
        store: bool = True,
    ) -> None:
        metadata = {"loop_closure_frame": self.frames, "session": self._session}
        if new_segment:
            metadata["segment_start"] = True
        if timestamp is not None:
            metadata["timestamp"] = float(timestamp)
        if not informative:
            metadata["uninformative"] = True
        if still:
            metadata["still"] = True
        if store:
            self._pending.append((v, name, position, metadata))
        self.map.append(v, name, None if position is None else tuple(float(c) for c in position)[:2], metadata)
        self._seams.add(new_segment)
        self._has_positions = self._has_positions and position is not None
        self._has_times = self._has_times and timestamp is not None
        if len(self._pending) >= self.commit_every:
            self.flush()

    # ------------------------------------------------------------------ resuming a traverse
    def resume(self, frames: int, last_thumbnail: np.ndarray | None = None) -> list[Closure]:
        """Take the database's last ``frames`` places as this traverse's first frames (a run that
        was interrupted after storing them) and replay their decisions from the stored vectors,
        times, positions and gate flags, without storing anything: every state a decision reads
        (rows for sequences, the recent past, the consistency gate, which places are
        uninformative) is rebuilt as the interrupted run had it. Returns the closures those
        frames accepted (the events the interrupted run wrote, or was about to write).
        ``last_thumbnail``: the last stored frame's grey thumbnail (its
        :class:`~fdnet.decisions.loop_gates.FrameSignals`), so the still-robot gate compares the
        next frame with it."""
        if self.frames:
            raise ConfigError("resume() must come before the first frame is processed")
        if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or not 0 <= frames <= self.places:
            raise ConfigError(f"cannot resume {frames!r} frames of a database of {self.places} places")
        frames = int(frames)
        start = self.places - frames
        vectors = self.map.vectors.view()[start:].copy()
        names = self.map.names[start:]
        informative = self.map.loop_column("informative").view()[start:].copy()
        still = self.map.loop_column("still").view()[start:].copy()
        starts = set(self._seams.starts.tolist())
        segment_start = [start + k in starts for k in range(frames)]
        sessions = self.map.loop_column("session")
        if frames and sessions[start] is not None:
            self._session = sessions[start]  # the interrupted traverse goes on: one session
        times = self.map.loop_column("timestamp")[start:]
        positions = self.map.positions[start:]
        self.map.truncate(start)
        self._seams.truncate(start)
        self._has_times = self.map.loop_column("timestamp").all_present()
        self._has_positions = self.map.positions.all_present()
        self._start_traverse()
        for k in range(frames):
            self.process_vector(
                vectors[k],
                timestamp=times[k],
                name=names[k],
                position=positions[k],
                _replay={
                    "informative": bool(informative[k]),
                    "still": bool(still[k]),
                    "segment_start": segment_start[k],
                },
            )
        self._last_thumbnail = None if last_thumbnail is None else np.asarray(last_thumbnail, np.float32)
        return list(self.closures)

    def flush(self) -> None:
        """Store the frames not stored yet, in one transaction."""
        if not self._pending:
            return
        vectors, names, positions, metadata = zip(*self._pending)
        result = self.database.add(
            np.stack(vectors),
            list(names),
            None if all(p is None for p in positions) else list(positions),
            metadata=list(metadata),
            allow_duplicates=self.allow_duplicates,
        )
        self._pending = []
        if result.added != len(names):
            raise DataError(
                f"{self.database.path}: already holds place(s) named {', '.join(result.skipped[:3])} "
                "(added by another process?); they were not added again"
            )
        if result.places != self.places:
            # Another process added places since we last looked: reload, so place indices stay
            # the database's (rare; the whole map is read again).
            self._load_places()
        else:
            self._read_stored_vectors(result.places)

    def _read_stored_vectors(self, places: int) -> None:
        """Once the database keeps its vectors in a file (from its ``compressed_from`` places),
        the map reads the stored frames from there instead of keeping them in memory."""
        stored = self.database.stored_vectors(places)
        if stored is None:
            return
        if isinstance(self.map.vectors, FileRows):
            self.map.vectors.stored(places)
            return
        self.map.vectors = stored  # this add reached the size: the copy in memory is dropped
        if self.candidates.indexed is not None:
            self.candidates.indexed.compressed_from = 0  # and the index keeps codes, not vectors

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
