"""Which places a loop-closure frame may match, and how each scores: the search half of
:class:`~fdnet.decisions.loop_closure.LoopClosureDetector` (the other half is gates, rule and
consistency).

For frame t of a traverse, :class:`LoopCandidates` finds the first frame that is still the
robot's recent past (:class:`~fdnet.decisions.loop_gates.RecentPast`: ``exclude_last``, a still
segment, seconds, metres; and the frames it still resembles more than unrelated places,
:func:`~fdnet.decisions.loop_recency.similar_past`), so that only a prefix of the map is
searchable, and scores that prefix: every place (one similarity row; with sequences the row is
kept, padded at each seam, and the one sequence scorer sums the last L rows), or through an
index on large maps (:mod:`fdnet.decisions.loop_search`). Uninformative places take a neutral
value in sequences and are never the best candidate.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from fdnet.decisions.loop_gates import LoopGates, RecentPast
from fdnet.decisions.loop_recency import (
    RECENT_WINDOW,
    Seams,
    relative_to_segments,
    sampled_similar_past,
    segment_levels,
    similar_past,
)
from fdnet.decisions.loop_threads import single_blas_thread


@dataclass(frozen=True)
class FrameQuery:
    """One frame as the search sees it: its vector, its index ``t`` in the traverse, the places
    in the map before it (``count``), its gate flags, and its time and position (or None)."""

    vector: np.ndarray
    t: int
    count: int
    informative: bool = True
    still: bool = False
    timestamp: float | None = None
    position: tuple | None = None


@dataclass(frozen=True)
class SearchPlan:
    """What the search is: the descriptor's ``similarity``, ``sequence_length`` (1 = single
    images), ``first_full`` (the neutral columns padding each segment,
    :func:`~fdnet.matching.sequence.sequence_reach`), ``depth`` (candidates the rule reads),
    the ``gates`` and ``exclude_last``."""

    similarity: object
    sequence_length: int
    first_full: int
    depth: int
    gates: LoopGates
    exclude_last: int = 0


class LoopCandidates:
    """The search's state over one traverse (see the module docstring): per frame, the places in
    the map before it, the first frame its own recent past reached, how far back its exclusion
    went (:attr:`excluded_back`), and with sequences the last L - 1 similarity rows."""

    def __init__(self, plan: SearchPlan):
        self.plan = plan
        self.before: list[int] = []
        self._rows: deque[np.ndarray] = deque(maxlen=max(plan.sequence_length - 1, 0) or None)
        self._recent = RecentPast(plan.exclude_last, plan.gates)
        #: the current segment's first frame of this traverse
        self.segment_first = 0
        self._own_first: list[int] = []
        #: per frame: how many frames back its exclusion went
        self.excluded_back: list[int] = []
        #: frames whose exclusion reached further back than exclude_last (a still robot)
        self.still_exclusions = 0
        #: the index over the map (:class:`~fdnet.decisions.loop_search.IndexedCandidates`), once in use
        self.indexed = None

    def new_segment(self, t: int) -> None:
        """Frame ``t`` starts a new recording: no sequence reaches back past it."""
        self.segment_first = t
        self._rows.clear()

    def use_index(self, dim: int, compressed_from: int | None = None) -> None:
        from fdnet.decisions.loop_search import COMPRESSED_FROM, IndexedCandidates

        compressed_from = COMPRESSED_FROM if compressed_from is None else compressed_from
        self.indexed = IndexedCandidates(dim, self.plan.sequence_length, compressed_from=compressed_from)

    def frame_done(self, count: int) -> None:
        """The frame is decided and added: ``count`` places were in the map before it."""
        self.before.append(count)

    def candidates(self, frame: FrameQuery, places, seams: Seams) -> tuple[np.ndarray, np.ndarray, int]:
        """(candidate places best first, their scores, how many places were searchable) for
        ``frame`` over the map ``places`` (:class:`~fdnet.matching.place_map.PlaceMap`) and its
        ``seams``."""
        if self.indexed is not None:
            return self._indexed_candidates(frame, places, seams)
        return self._exhaustive_candidates(frame, places, seams)

    def _exhaustive_candidates(self, frame: FrameQuery, places, seams: Seams):
        v, t, count = frame.vector, frame.t, frame.count
        if count:
            with single_blas_thread():
                row = np.asarray(self.plan.similarity(v[None], places.vectors.view()), dtype=np.float32)[0]
        else:
            row = np.zeros(0, np.float32)
        previous = float(row[count - 1]) if t > 0 and count > 0 else None
        informative = places.loop_column("informative")
        raw = row
        row, neutral = _mask_uninformative(row, frame.informative, informative)
        back = self._similar_back(frame, places, row)
        searchable = self._searchable(frame, previous, back)
        every = np.arange(len(raw))
        levels = segment_levels(raw, every, seams.starts)
        if levels is not None:  # each segment's places against the frame's level there
            relative = relative_to_segments(raw, every, seams.starts, levels)
            row, neutral = _mask_uninformative(relative, frame.informative, informative)
        if self.plan.sequence_length > 1:
            from fdnet.matching.sequence import online_sequence_scores

            # Each segment of the map starts with first_full neutral columns (the row's median):
            # a sequence that would run off the start of its segment is scored over all L frames,
            # the missing ones neutral, instead of over the few it has (a mean of one or two
            # similarities is noisy and would win by chance) or over another recording's frames.
            # The whole row is kept for the next frames' sequences; only the searchable places
            # are scored.
            if neutral is None:  # nothing was masked: the row's own median, computed only here
                neutral = float(np.median(row)) if len(row) else 0.0
            padded = seams.padded(row, neutral)
            scores = online_sequence_scores([*self._rows, padded], seams.width(searchable))
            scores = scores[seams.columns(searchable)]
            self._rows.append(padded)
        else:
            scores = row[:searchable]
        if not searchable:
            return np.zeros(0, np.int64), np.zeros(0, np.float32), 0
        from fdnet.matching.similarity import top_k_of_matrix

        scores = _never_best(scores, informative)
        idx, top = top_k_of_matrix(scores[None], min(self.plan.depth, len(scores)))
        return idx[0], top[0], searchable

    def _indexed_candidates(self, frame: FrameQuery, places, seams: Seams):
        from fdnet.decisions.loop_search import MapSegments

        v, t, count = frame.vector, frame.t, frame.count
        vectors = places.vectors.view()
        previous = (
            float(self.plan.similarity(v[None], vectors[count - 1 : count])[0, 0]) if t > 0 and count > 0 else None
        )
        back = self._similar_back(frame, places)
        searchable = self._searchable(frame, previous, back)
        mask = places.loop_column("informative").view(count)
        levels, neutral = self.indexed.scale(v, vectors, mask, seams.starts)
        if t == self.segment_first:
            self.indexed.new_segment()
        own_start = self.before[self.segment_first] if self.segment_first < t else count
        segments = MapSegments(seams, levels, own_start)
        ids, scores = self.indexed.search(v, vectors, searchable, mask, neutral, frame.informative, segments)
        depth = max(self.plan.depth, 1)
        return ids[:depth], scores[:depth], searchable

    def _similar_back(self, frame: FrameQuery, places, row: np.ndarray | None = None) -> int:
        """How many of its segment's earlier frames the frame still resembles more than unrelated
        places (:func:`~fdnet.decisions.loop_recency.similar_past` over its ``row``; without one,
        on the indexed path, over a sample of the map); an uninformative frame's row says
        nothing, so it keeps its predecessor's reach, one frame further."""
        t = frame.t
        if t <= self.segment_first or not self.plan.gates.similar_past:
            return 0
        if not frame.informative:
            return (t - self._own_first[-1]) if self._own_first else 0
        if row is None:
            recent = np.asarray(self.before[max(self.segment_first, t - RECENT_WINDOW) : t], np.int64)[::-1]
            vectors = places.vectors.view()  # (the indexed path: it holds the map's sample)
            return sampled_similar_past(
                self.plan.similarity, frame.vector, vectors, recent, self.indexed.map_sample(vectors)
            )
        return similar_past(row, np.asarray(self.before[self.segment_first : t], np.int64)[::-1])

    def _searchable(self, frame: FrameQuery, previous: float | None, back: int = 0) -> int:
        """How many places frame ``t`` may match (a prefix of the map): places from earlier
        sessions and this traverse's frames before its recent past (:class:`RecentPast`:
        exclude_last, the current still segment, the last seconds or metres; and the ``back``
        frames it still resembles, :meth:`_similar_back`), for sequences the recent past of
        every frame of the query's sequence, moved back by sequence_length - 1 frames more, so
        that no candidate's sequence shares a frame with the query's own."""
        t, exclude_last = frame.t, self.plan.exclude_last
        first = self._recent.first_excluded(t, previous, frame.still, frame.timestamp, frame.position)
        by_count = max(t - exclude_last, 0) if exclude_last else t
        if first < by_count:  # the still segment, seconds or metres reached further back
            self.still_exclusions += 1
        first = min(first, t - back)
        self._own_first.append(first)
        length = self.plan.sequence_length
        if length > 1:
            first = min(self._own_first[max(self.segment_first, t - length + 1) :])
            moved = first - (length - 1)
            first = max(moved, self.segment_first) if first >= self.segment_first else moved
        first = max(first, 0)
        self.excluded_back.append(t - first)
        return frame.count if first >= t else self.before[first]


def _mask_uninformative(row: np.ndarray, informative: bool, places_informative) -> tuple[np.ndarray, float | None]:
    """(the frame's similarity row with uninformative places, and for an uninformative frame
    every place, set to the median of its informative values, that value): neutral in a
    sequence (a sequence through a tunnel is scored by its other frames), and below the best
    candidate. :func:`_never_best` then keeps uninformative places from being matched at all.
    The median is the row's median too (copies of a median keep it), so the sequence padding
    reuses it; None when nothing needed masking (the common case: no median is computed)."""
    if not len(row):
        return row, 0.0
    mask = places_informative.view(len(row))
    if informative and mask.all():
        return row, None
    neutral = float(np.median(row[mask])) if mask.any() else 0.0
    if not informative:
        return np.full_like(row, neutral), neutral
    row = row.copy()
    row[~mask] = neutral
    return row, neutral


def _never_best(scores: np.ndarray, places_informative) -> np.ndarray:
    """``scores`` with uninformative places at the lowest informative score."""
    mask = places_informative.view(len(scores))
    if mask.all() or not mask.any():
        return scores
    scores = np.array(scores, dtype=np.float32)
    scores[~mask] = scores[mask].min()
    return scores
