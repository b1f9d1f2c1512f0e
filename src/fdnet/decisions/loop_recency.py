"""What a loop-closure frame may not match, found from the traverse itself: the robot's recent past
and the seams between recordings.

**The recent past, estimated online** (:func:`similar_past`). A frame resembles the frames just
before it because the robot has not yet left the place, and how long that lasts depends on the
speed, the frame rate and the scene (Nordland's train moves on within 5 frames, Gardens Point's
walker still sees the same corridor 15 frames later). So no frame count is right on every route.
Instead, each frame walks back through its own traverse while it still resembles those frames
more than it resembles unrelated places: the *null level* (:func:`null_level`) is the 90th
percentile of the frame's similarity to the places outside its recent past (a revisit is a handful
of places among many and barely moves it; estimated again without the frames the walk passed until
the walk stops changing), and the walk stops after :data:`PATIENCE` consecutive frames below it.
Everything the walk passed is excluded. It reads only the frame's own similarity row and earlier
frames: causal, and free of settings a user must tune.

**Seams** (:class:`Seams`). A traverse is made of *segments*: one recording driven without a break.
A new pass of a route (``--data --conditions``), places from an earlier session in the database, a
bag's or video's gap in time start a new one. A sequence never spans a seam: the query's own
sequence starts again (the frame decides only once it has a whole sequence in its segment), and
on the map side each segment is scored as if it began the map, so that a sequence ending at the
first frame of the second pass never reads the last frames of the first as its predecessors
(as if the robot had driven from the end of the line to its start). This is done with *columns*:
every place has a column in a row that leaves ``pad`` neutral columns before each segment, and the
sequence scorer runs over those rows unchanged.

**One scale across segments** (:func:`segment_levels`). A frame resembles the places of a
recording driven in its own light or season more than those of another, whatever the place: a
summer frame's similarities to the summer pass run higher than to the winter pass, so a look-alike
in its own recording can outscore the true place in another. So, once the map holds more than one
segment, each similarity is taken relative to the frame's null level against that segment (the
same 90th percentile as above, of its similarities to that segment's places): each recording is
scored by how much more the frame resembles a place there than it resembles that recording's
unrelated places. The walk back through the recent past reads the similarities themselves.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

#: below-level frames in a row that end the walk back through the recent past (a frame or two
#: below can be noise: a passing car, a blink of the exposure, a 64x32 frame's grain)
PATIENCE = 5
#: the quantile of the frame's similarities to the places outside its recent past that counts as
#: "like an unrelated place" (a revisit is a handful of places among many, so barely moves it)
NULL_QUANTILE = 0.9
#: places sampled (evenly) for the null level on large maps
NULL_SAMPLE = 4096
#: a segment's own level (:func:`segment_levels`) needs this many of its places, so that four lie
#: above its 90th percentile; a smaller one is measured against the level of all of them
LEVEL_PLACES = 40
#: the level is re-estimated without the frames the walk passed, until the walk stops changing
#: (it converges in 2-3 rounds on the development routes)
MAX_ROUNDS = 5
#: a time gap larger than this many times the recent median frame interval starts a new segment
GAP_FACTOR = 10.0


def null_level(similarities: np.ndarray) -> float:
    """The similarity above which a place still resembles the frame more than unrelated places
    do: the :data:`NULL_QUANTILE` quantile of its similarities (an even sample on large maps)."""
    values = np.asarray(similarities, dtype=np.float64)
    if len(values) > NULL_SAMPLE:
        values = values[np.linspace(0, len(values) - 1, NULL_SAMPLE).astype(np.int64)]
    return float(np.quantile(values, NULL_QUANTILE)) if len(values) else math.inf


def walk_back(back: np.ndarray, level: float, patience: int = PATIENCE) -> int:
    """How many frames back the recent past reaches: ``back[k]`` is the frame's similarity to the
    frame k + 1 steps earlier (newest first); the walk passes frames at or above ``level`` and
    stops at the first ``patience`` consecutive frames below it. Returns the count of frames up
    to and including the last one at or above the level (0: not even the previous frame)."""
    back = np.asarray(back, dtype=np.float64)
    # a short segment's frames are few and its null level rests on few places: unrelated frames
    # cross it more often than on a long one, so a walk there may not bridge as many of them
    patience = min(patience, max(1, len(back) // 4))
    above = back >= level
    if not above.any():
        return 0
    below = (~above).astype(np.int64)
    # the first run of `patience` below-level frames: a window sum of the below mask
    runs = np.convolve(below, np.ones(patience, np.int64), mode="valid") if len(below) >= patience else []
    stops = np.flatnonzero(np.asarray(runs) == patience)
    end = int(stops[0]) if len(stops) else len(above)
    passed = np.flatnonzero(above[:end])
    return int(passed[-1]) + 1 if len(passed) else 0


def similar_past(row: np.ndarray, recent: np.ndarray) -> int:
    """How many of its segment's earlier frames a frame still resembles more than unrelated
    places. ``row``: its similarity to every place of the map; ``recent``: the places of the
    frames of its segment before it, newest first. The level starts as :func:`null_level` of the
    whole row and is estimated again from the places outside the frames the walk passed
    (:data:`PATIENCE` more kept out), until the walk stops changing; with fewer than 10 places
    outside, the walk keeps its last reach (early in a traverse everything is recent)."""
    row = np.asarray(row, dtype=np.float64)
    back = row[recent]
    reach = walk_back(back, null_level(row))
    for _ in range(MAX_ROUNDS):
        outside = np.ones(len(row), dtype=bool)
        outside[recent[: reach + PATIENCE]] = False
        if outside.sum() < 10:
            break
        again = walk_back(back, null_level(row[outside]))
        if again == reach:
            break
        reach = again
    return reach


#: how many recent frames of its segment a frame walks back through at most on the indexed path
RECENT_WINDOW = 2000


def segment_levels(similarities: np.ndarray, places: np.ndarray, starts: np.ndarray) -> np.ndarray | None:
    """The frame's null level against each segment of the map (``starts``: each segment's first
    place, in order), from its ``similarities`` to ``places`` (every place, or a sample): the
    :data:`NULL_QUANTILE` quantile of those in the segment, or of all of them for a segment with
    fewer than :data:`LEVEL_PLACES` (an even sample of :data:`NULL_SAMPLE` when more are given).
    None for a map of one segment: there is nothing to put on one scale."""
    starts = np.asarray(starts, np.int64)
    if len(starts) < 2:
        return None
    values, places = np.asarray(similarities, np.float64), np.asarray(places, np.int64)
    if len(values) > NULL_SAMPLE:
        pick = np.linspace(0, len(values) - 1, NULL_SAMPLE).astype(np.int64)
        values, places = values[pick], places[pick]
    levels = np.full(len(starts), float(np.quantile(values, NULL_QUANTILE)) if len(values) else 0.0)
    segment = np.searchsorted(starts, places, side="right") - 1
    # every segment's quantile from one sort (a map of many sessions has many segments): values
    # sorted within segments, then numpy's linear interpolation between order statistics
    ordered = values[np.lexsort((values, segment))]
    counts = np.bincount(segment, minlength=len(starts))
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    own = np.flatnonzero(counts >= LEVEL_PLACES)
    position = NULL_QUANTILE * (counts[own] - 1)
    below = np.floor(position).astype(np.int64)
    above = np.minimum(below + 1, counts[own] - 1)
    low, high = ordered[first[own] + below], ordered[first[own] + above]
    levels[own] = low + (high - low) * (position - below)
    return levels


def relative_to_segments(similarities: np.ndarray, places: np.ndarray, starts: np.ndarray, levels) -> np.ndarray:
    """``similarities`` to ``places`` minus the level (:func:`segment_levels`) of each place's
    segment; unchanged when ``levels`` is None."""
    if levels is None:
        return similarities
    segment = np.searchsorted(np.asarray(starts, np.int64), np.asarray(places, np.int64), side="right") - 1
    return (np.asarray(similarities) - levels[segment]).astype(np.asarray(similarities).dtype, copy=False)


def sampled_similar_past(similarity, vector: np.ndarray, vectors, recent: np.ndarray, sample: tuple) -> int:
    """:func:`similar_past` on a map too large to score whole: the frame's similarity to its
    ``recent`` places (newest first) and to an even ``sample`` of the map (the null level), as
    (place ids, their vectors) held by the caller, its recent places left out; by the
    descriptor's ``similarity``."""
    ids, rows = sample
    outside = ~np.isin(ids, recent, assume_unique=True)
    # the whole sample is scored and its recent places dropped after: cheaper than copying the rest
    row = np.concatenate([similarity(vector[None], vectors[recent])[0], similarity(vector[None], rows)[0][outside]])
    return similar_past(np.asarray(row, np.float64), np.arange(len(recent)))


class Seams:
    """Which segment each place belongs to and its column in a padded row (see the module
    docstring): ``pad`` neutral columns before every segment, so that a sequence of
    ``sequence_length`` frames at any velocity never reaches into the previous segment. Only the
    segments' first places are held: place i of the s-th segment (from 1) is column i + s x pad,
    so a map of 10^7 places costs nothing per place here."""

    def __init__(self, pad: int):
        self.pad = int(pad)
        self._count = 0
        self._segment_starts: list[int] = []  # place index of each segment's first place

    def __len__(self) -> int:
        return self._count

    def add(self, new_segment: bool) -> None:
        """Add the next place; ``new_segment``: it starts a segment (the first place always does)."""
        if new_segment or self._count == 0:
            self._segment_starts.append(self._count)
        self._count += 1

    def truncate(self, count: int) -> None:
        """Forget the places from ``count`` on (a traverse being replayed)."""
        self._count = min(int(count), self._count)
        self._segment_starts = [s for s in self._segment_starts if s < self._count]

    def columns(self, count: int | None = None) -> np.ndarray:
        """The first ``count`` places' columns (None: every place's)."""
        count = self._count if count is None else min(int(count), self._count)
        starts = [s for s in self._segment_starts if s < count]
        segment = np.repeat(np.arange(1, len(starts) + 1), np.diff([*starts, count]))
        return np.arange(count, dtype=np.int64) + self.pad * segment

    def width(self, count: int) -> int:
        """The padded row's length for the first ``count`` places."""
        return count + self.pad * bisect.bisect_right(self._segment_starts, count - 1) if count else 0

    def padded(self, row: np.ndarray, neutral: float) -> np.ndarray:
        """``row`` (the first len(row) places) laid out in columns, the padding ``neutral``."""
        count = len(row)
        out = np.full(self.width(count), neutral, dtype=np.float32)
        out[self.columns(count)] = row
        return out

    def first_places(self, places: np.ndarray) -> np.ndarray:
        """The first place of the segment that holds each of ``places``."""
        starts = self.starts
        if not len(starts):
            return np.zeros(np.shape(places), np.int64)
        return starts[np.maximum(np.searchsorted(starts, places, side="right") - 1, 0)]

    @property
    def starts(self) -> np.ndarray:
        """The first place of each segment, in order."""
        return np.asarray(self._segment_starts, np.int64)

    @property
    def segments(self) -> int:
        return len(self._segment_starts)


class GapDetector:
    """Whether a frame's timestamp starts a new segment: a gap over :data:`GAP_FACTOR` times the
    median of the last intervals (a bag recorded in two sittings, a video cut)."""

    def __init__(self, history: int = 50):
        self._intervals: list[float] = []
        self._last: float | None = None
        self.history = int(history)

    def gap(self, timestamp: float | None) -> bool:
        if timestamp is None:
            self._last = None
            return False
        last, self._last = self._last, float(timestamp)
        if last is None:
            return False
        interval = float(timestamp) - last
        typical = float(np.median(self._intervals)) if len(self._intervals) >= 3 else None
        if typical is not None and typical > 0 and interval > GAP_FACTOR * typical:
            return True
        self._intervals.append(interval)
        del self._intervals[: -self.history]
        return False
