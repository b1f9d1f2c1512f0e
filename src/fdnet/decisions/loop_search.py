"""Candidate search for loop closure on large maps: an inverted-file index instead of every place.

Exhaustive search scores a frame against every place: one (places x dim) product and, with
sequences, L shifted sums over the whole row per velocity. That is milliseconds at 10^4 places
and tens of milliseconds at 10^5. Above a size (:data:`INDEX_FROM` places by default) the
detector switches to :class:`IndexedCandidates`:

1. each frame's nearest places come from a faiss IVF-Flat index
   (:class:`fdnet.matching.index.VectorIndex`, ``ivf``) that grows with the map: frames are added
   as they are seen, and the cells are trained again when the map has grown fourfold since they
   were trained (k-means is seeded, so the same map gives the same cells: a resumed run replays
   the same decisions);
2. without sequences the candidates are those places; with sequences of L frames, a candidate
   sequence end is any place a recent frame's neighbour points to (place p of the frame k steps
   back, moved on by k x v places for each velocity v), and each such end is scored by
   :func:`fdnet.matching.sequence.online_sequence_scores`, the exhaustive path's scorer, over
   rows read from the stored vectors at the pairs the sum needs, so the sequence score of every
   place the search proposes is exact; places it does not propose are not scored;
3. the missing terms of a sequence that runs off the start of the map, and the places a gate
   marked uninformative, take the frame's neutral value (its median similarity, estimated on an
   evenly spaced sample of the map), as in the exhaustive path.

Above a larger size (:data:`COMPRESSED_FROM` places by default, the detector's
``compressed_from``) step 1's index is :class:`fdnet.matching.compressed.CompressedIndex`
instead: 4-bit product-quantised codes in memory (tens of bytes per place instead of 4 x dim),
each frame's short list re-ranked by exact dot products with the stored vectors, so the
neighbours and their similarities are exact and steps 2 and 3 are unchanged. When the
database keeps its vectors in a file (:mod:`fdnet.matching.database.vector_store`), ``vectors``
is a :class:`~fdnet.matching.file_rows.FileRows` and every step reads only the rows it needs.

An approximate search can miss a place the exhaustive one would rank first: the figures of
``fdnet benchmark --parts loop`` give the agreement with exhaustive decisions next to the speed.
"""

from __future__ import annotations

import contextlib
from collections import deque
from dataclasses import dataclass

import numpy as np

from fdnet.decisions.loop_recency import NULL_SAMPLE, relative_to_segments, segment_levels
from fdnet.matching.index import one_faiss_thread
from fdnet.matching.sequence import DEFAULT_VELOCITIES, SequenceRow, sequence_places, sequence_reach

#: maps of at least this many places are searched through the index (``search="auto"``)
INDEX_FROM = 20_000
#: below this many places the "index" is exact (faiss flat): k-means needs points to train on
IVF_FROM = 4096
#: maps of at least this many places are searched through compressed codes (``compressed_from``)
COMPRESSED_FROM = 2_000_000
#: neighbours fetched per frame from the index
NEIGHBOURS = 32
#: sequence ends scored exactly per frame (the best of a first ranking from the index's own similarities)
RESCORED = 64
#: places sampled to estimate a frame's median similarity (its neutral value)
MEDIAN_SAMPLE = 512

#: a block of frames described ahead is searched on all of faiss's threads from this many places
#: (one frame, or a smaller map: on one). The scan of the fast-scan codes for 9 frames ran 1.5-1.8x
#: faster on 2 threads at 3 x 10^6-10^7 places on an idle 2-core machine; at 10^6 the detector's
#: decision gained nothing and its blocks' first frames were slower (docs/performance.md)
BLOCK_ON_ALL_THREADS_FROM = COMPRESSED_FROM


def sample_count(count: int) -> int:
    """The map size an even sample of the map is drawn over: ``count`` rounded down to a
    multiple of a sixteenth of its highest power of two (so within 1/16 of it, and the same
    for every count up to the next multiple)."""
    step = 1 << max(int(count).bit_length() - 5, 0)
    return int(count) - int(count) % step


@dataclass(frozen=True)
class MapSegments:
    """The map's segments as one frame sees them: ``seams``
    (:class:`~fdnet.decisions.loop_recency.Seams`), the frame's ``levels`` against each
    (:meth:`IndexedCandidates.levels`; None: one segment, nothing to put on one scale) and
    ``own_start``, the first place of the frame's own segment."""

    seams: object = None
    levels: np.ndarray | None = None
    own_start: int | None = None


class IndexedCandidates:
    """The index over a detector's places and the recent frames' neighbours (see the module
    docstring). ``vectors``: a callable giving the detector's (places, dim) vectors so far."""

    def __init__(
        self,
        dim: int,
        sequence_length: int,
        neighbours: int = NEIGHBOURS,
        probe: int = 32,
        compressed_from: int = COMPRESSED_FROM,
    ):
        from fdnet.matching.index import IndexSettings, VectorIndex

        self.dim = int(dim)
        self.sequence_length = int(sequence_length)
        self.neighbours = int(neighbours)
        self.compressed_from = int(compressed_from)
        self._make = lambda kind: VectorIndex(self.dim, IndexSettings(kind=kind, ivf_probe=int(probe)))
        self._index = None
        self._trained_on = 0
        # per recent frame: (its vector, its neighbours' place ids, its neutral value, places then)
        self._recent: deque = deque(maxlen=max(self.sequence_length, 1))
        # (the map size it was drawn over, place ids, their vectors, the median's subset of them)
        self._sample: tuple | None = None
        #: a callable giving (a :class:`~fdnet.matching.database.codes_cache.CodesCache`, the
        #: vector file it is for), or None: the compressed codes are loaded from that cache when
        #: it matches the map's first places, and codes trained here are written to it
        self.codes_source = None
        # compressed search by blocks (see :meth:`_compressed_neighbours`): frames the block has
        # left, the places the index holds for it, upcoming frames' results, upcoming vectors
        self.block = max(self.sequence_length - 1, 1)
        self._block_left, self._frozen = 0, 0
        self._ahead: deque = deque()
        self._upcoming = np.zeros((0, self.dim), np.float32)
        # (the first place of the frames' own segment, its rows read so far): see _own_segment_rows
        self._own = None

    def __len__(self) -> int:
        return 0 if self._index is None else len(self._index)

    def sync(self, vectors: np.ndarray) -> None:
        """Index every place of ``vectors`` not indexed yet; train the cells again (and re-add
        everything) when the map has grown fourfold since they were trained."""
        count = len(vectors)
        if count == 0:
            return
        if self._compressed(count):
            from fdnet.matching.compressed import CompressedIndex

            first = not isinstance(self._index, CompressedIndex)
            if first:
                self._index = self._cached_codes(count) or CompressedIndex(self.dim)
            # a frame's add on one thread; training and bulk encoding (a loaded cache's missing
            # places too) keep every thread
            with one_faiss_thread() if count - len(self._index) < 1000 else contextlib.nullcontext():
                self._index.sync(vectors)  # it trains again itself as the map grows
            if first and self._index.trainings:
                self._save_codes()
            return
        if self._index is None or count >= 4 * max(self._trained_on, 1):
            # below IVF_FROM places exact search is as fast and k-means would have too few points
            self._index = self._make("flat" if count < IVF_FROM else "ivf")
            self._index.add(vectors)
            self._index.build()
            self._trained_on = count
        elif count > len(self._index):
            with one_faiss_thread():  # a frame or a few: training and bulk adds keep every thread
                self._index.add(vectors[len(self._index) : count])

    def _codes(self):
        """(codes cache, vector file) from :attr:`codes_source`, or None."""
        return None if self.codes_source is None else self.codes_source()

    def _cached_codes(self, count: int):
        """The database's cached codes when they were built from at most its first ``count``
        places (the rest are encoded, not trained); else None."""
        source = self._codes()
        return None if source is None else source[0].load(source[1], count)

    def _save_codes(self) -> None:
        """Leave codes trained here in the database's cache when each of their places is a row
        the database has committed to its file (for the next run, and a resumed one)."""
        source = self._codes()
        if source is not None and len(self._index) <= len(source[1]):
            source[0].save(self._index, source[1], force=True)

    def _compressed(self, count: int) -> bool:
        # below IVF_FROM places the index is exact anyway, and the codebooks would lack points
        return count >= max(self.compressed_from, IVF_FROM)

    def map_sample(self, vectors) -> tuple[np.ndarray, np.ndarray]:
        """(place ids, vectors) of an even sample of :data:`~fdnet.decisions.loop_recency.NULL_SAMPLE`
        places of the map ``vectors``, held in memory: drawn over the first
        :func:`sample_count` places, so it depends on the map's size alone (a resumed run draws
        the same) and is read from the map again only when that has grown by a sixteenth. A map
        kept in a file would otherwise be read at thousands of scattered rows a frame."""
        count = sample_count(len(vectors))
        if self._sample is None or self._sample[0] != count:
            ids = np.linspace(0, count - 1, min(NULL_SAMPLE, count)).astype(np.int64)
            rows = np.asarray(vectors[ids], dtype=np.float32)
            pick = np.linspace(0, len(ids) - 1, min(MEDIAN_SAMPLE, len(ids))).astype(np.int64)
            self._sample = (count, ids, rows, np.ascontiguousarray(rows[pick]), pick)
        return self._sample[1], self._sample[2]

    def scale(self, v: np.ndarray, vectors, informative: np.ndarray, starts: np.ndarray) -> tuple:
        """(the frame's null level against each segment of the map, its neutral value), both over
        the :meth:`map_sample`. The levels: :func:`~fdnet.decisions.loop_recency.segment_levels`,
        None for a map of one segment (``starts``: each segment's first place). The neutral value:
        the frame's median similarity over :data:`MEDIAN_SAMPLE` informative places of the sample
        (all of its informative places when fewer), each relative to its segment's level. With
        levels, one product with the whole sample serves both."""
        ids, rows = self.map_sample(vectors)
        sims = rows @ v if len(starts) >= 2 else None
        levels = None if sims is None else segment_levels(sims, ids, starts)
        usable = informative[ids]
        if not usable.any():  # (an empty map too)
            return levels, 0.0
        if usable.all():  # the usual map: the subset drawn with the sample
            pick = self._sample[4]
            values = self._sample[3] @ v if sims is None else sims[pick]
        else:
            kept = np.flatnonzero(usable)
            pick = kept[np.linspace(0, len(kept) - 1, min(MEDIAN_SAMPLE, len(kept))).astype(np.int64)]
            values = rows[pick] @ v if sims is None else sims[pick]
        return levels, float(np.median(relative_to_segments(values, ids[pick], starts, levels)))

    def new_segment(self) -> None:
        """The next frame starts a new recording: no sequence reaches back past it (and a new
        block of the compressed search starts with it)."""
        self._recent.clear()
        self._block_left = 0
        self._ahead.clear()

    def look_ahead(self, vectors: np.ndarray) -> None:
        """The vectors (n, dim) of the frames that will come next, in order (a batch already
        described): the compressed search proposes their neighbours in the same call as the next
        block's first frame's. Answers do not depend on it; only the time does."""
        self._upcoming = vectors

    def _compressed_neighbours(
        self, v: np.ndarray, vectors, k: int, below: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The compressed index's ``k`` neighbours of ``v`` (exact similarities), by blocks of
        :attr:`block` = L - 1 frames: at a block's first frame the index takes every place of
        the map, and every frame of the block is searched among those places only. The places
        the block's own frames add are never searchable by them (a frame may match no place of
        its own sequence's last L - 1 frames, and a block starts again at each segment), so no
        place a frame may match is left out; the block's frames can be searched in one call
        (faiss's scan over the codes serves them all: :meth:`look_ahead`), and a robot feeding
        one frame at a time gets the same answers. ``below``: only places before that one (the
        block's frames are in one segment, so they share it)."""
        from fdnet.matching.file_rows import FileRows

        starting = self._block_left == 0
        upcoming, self._upcoming = self._upcoming, self._upcoming[:0]
        self._block_left = (self.block if starting else self._block_left) - 1
        if starting:
            self.sync(vectors)
            self._frozen = len(vectors)
            queries = np.concatenate([v[None], upcoming[: self.block - 1]]).astype(np.float32, copy=False)
            self._ahead.clear()
        elif self._ahead and np.array_equal(self._ahead[0][0], v):
            _, ids, sims = self._ahead.popleft()
            return ids[None], sims[None]
        else:
            self._ahead.clear()
            queries = v[None]
        frozen = vectors.view(self._frozen) if isinstance(vectors, FileRows) else vectors[: self._frozen]
        # a block's frames share the scan over every code on all of faiss's threads (each takes
        # some of the frames); a single frame's search does not split, and OpenMP's start costs
        alone = len(queries) == 1 or self._frozen < BLOCK_ON_ALL_THREADS_FROM
        with one_faiss_thread() if alone else contextlib.nullcontext():
            found, scores = self._index.search(queries, min(k, self._frozen), frozen, below=below)
        self._ahead.extend(zip(queries[1:], found[1:], scores[1:]))
        return found[:1], scores[:1]

    def search(
        self,
        v: np.ndarray,
        vectors: np.ndarray,
        searchable: int,
        informative: np.ndarray,
        neutral: float,
        frame_informative: bool = True,
        segments: "MapSegments | None" = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Record the new frame and return its candidates: (place ids, scores) best first, all
        below ``searchable`` and informative; scores are single-image similarities, or with
        sequences the sequence scores of the proposed ends. ``segments``: the map's segments as
        the frame sees them (:class:`MapSegments`): a sequence ending in a segment counts the
        places before its start as missing (neutral), every similarity read is taken relative to
        the frame's level against its place's segment, and with levels the frame's neighbours
        are found among the earlier segments' places and, exactly, among its own segment's
        (:meth:`_neighbours`), all as on the exhaustive path."""
        segments = segments or MapSegments()
        seams, levels, own_start = segments.seams, segments.levels, segments.own_start
        count = len(vectors)
        compressed = self._compressed(count)
        if not compressed:
            self.sync(vectors)
            self._block_left = 0
        ids, sims = np.zeros(0, np.int64), np.zeros(0, np.float32)
        if count:
            split = levels is not None and own_start is not None and 0 < own_start < count
            found, scores = self._neighbours(v, vectors, compressed, own_start if split else None)
            keep = found >= 0
            order = np.argsort(found[keep])
            ids, sims = found[keep][order], scores[keep][order]  # sorted by place, for look-ups
        offsets = None if levels is None else (seams.starts, levels)
        self._recent.append((v, ids, neutral, count, frame_informative, sims, offsets))
        if searchable <= 0:
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        if self.sequence_length <= 1:
            ends = ids
        else:
            ends = self._sequence_ends(searchable)
        ends = np.unique(ends[(ends >= 0) & (ends < searchable)])
        ends = ends[informative[ends]]
        if not len(ends):
            return ends, np.zeros(0, np.float32)
        if self.sequence_length <= 1:
            scores = vectors[ends] @ v
            if offsets is not None:
                scores = relative_to_segments(scores, ends, *offsets)
        else:
            if len(ends) > RESCORED:
                # a first ranking from the similarities the index already returned (a pair it did
                # not return counts as neutral), then the best RESCORED ends exactly
                rough = self._sequence_scores(ends, vectors, informative, exact=False, seams=seams)
                ends = np.sort(ends[np.argsort(-rough, kind="stable")[:RESCORED]])
            scores = self._sequence_scores(ends, vectors, informative, seams=seams)
        order = np.lexsort((ends, -scores))  # best first, ties to the lower place
        return ends[order], scores[order].astype(np.float32)

    def _neighbours(self, v: np.ndarray, vectors, compressed: bool, own_start: int | None):
        """The frame's :attr:`neighbours` nearest places (ids, exact similarities). With
        ``own_start`` the map holds other segments than the frame's own, whose places resemble
        the frame more by their shared conditions alone and could fill its whole list: then the
        index gives the nearest places of the earlier segments, and the own segment's places
        (while fewer than :data:`INDEX_FROM`, the size up to which a whole map is scored
        exactly) are scored exactly and give theirs."""
        count = len(vectors)
        if own_start is not None and count - own_start > INDEX_FROM:
            own_start = None
        if compressed:  # exact similarities of the short list's best
            found, scores = self._compressed_neighbours(v, vectors, self.neighbours, below=own_start)
        else:
            with one_faiss_thread():
                found, scores = self._index.search(v[None], min(self.neighbours, count), below=own_start)
        found, scores = found[0], scores[0]
        if own_start is None:
            return found, scores
        similarity = self._own_segment_rows(vectors, own_start) @ v
        best = np.argsort(-similarity, kind="stable")[: self.neighbours]
        return np.concatenate([found, own_start + best]), np.concatenate([scores, similarity[best]])

    def _own_segment_rows(self, vectors, own_start: int) -> np.ndarray:
        """The rows of the places from ``own_start`` on (the frame's own segment), each read from
        the map once: a map in a file would otherwise be read at the whole segment every frame."""
        from fdnet.matching.place_map import GrowingArray

        if self._own is None or self._own[0] != own_start or len(self._own[1]) > len(vectors) - own_start:
            self._own = (own_start, GrowingArray(self.dim))
        rows = self._own[1]
        if own_start + len(rows) < len(vectors):
            rows.extend(np.asarray(vectors[np.arange(own_start + len(rows), len(vectors))], dtype=np.float32))
        return rows.view()

    def _sequence_ends(self, searchable: int) -> np.ndarray:
        """Proposed sequence ends: each recent frame's neighbours moved on by the frames since
        (a robot revisiting a route moves about one place per frame), widened by the slowest and
        fastest velocity's drift."""
        ends = []
        velocities = np.asarray(DEFAULT_VELOCITIES)
        for k, (_, ids, *_) in enumerate(reversed(self._recent)):
            low, high = int(np.floor(k * velocities.min())), int(np.ceil(k * velocities.max()))
            ends.append((ids[:, None] + np.arange(low, high + 1)[None, :]).ravel())
        return np.concatenate(ends) if ends else np.zeros(0, np.int64)

    def _sequence_scores(
        self, ends: np.ndarray, vectors: np.ndarray, informative: np.ndarray, exact: bool = True, seams=None
    ) -> np.ndarray:
        """Sequence scores of ``ends`` over the recent frames by
        :func:`~fdnet.matching.sequence.online_sequence_scores`, each frame a
        :class:`_RecentRow` read from the stored vectors (the frame's row held the places that
        existed then: later places count as missing). ``exact=False``: a pair's similarity only
        when the index returned that place for that frame, else neutral."""
        from fdnet.matching.sequence import online_sequence_scores

        # each end's segment's first place: a sequence ending in a segment counts the places
        # just before its start as neutral padding, as the exhaustive path's padded rows do
        first = np.zeros(len(ends), np.int64) if seams is None else seams.first_places(ends)
        pad = sequence_reach(self.sequence_length)
        if exact:  # every place the sums read, read once (a map in a file: one read, not one a frame)
            vectors = _Gathered(vectors, self._places_read(ends, len(vectors)))
        rows = [_RecentRow(recent, vectors, informative, first, pad, exact) for recent in self._recent]
        return online_sequence_scores(rows, ends=ends, exact_sums=True)

    def _places_read(self, ends: np.ndarray, count: int) -> np.ndarray:
        """The places the sums over the recent frames read for ``ends`` (the scorer's own
        :func:`~fdnet.matching.sequence.sequence_places` for each frame k steps back)."""
        velocities = np.asarray(DEFAULT_VELOCITIES, dtype=np.float64)
        places = np.unique([sequence_places(ends, k, velocities) for k in range(len(self._recent))])
        return places[(places >= 0) & (places < count)]


class _Gathered:
    """Rows ``ids`` of ``vectors`` read once; indexing by any of those ids reads from memory."""

    def __init__(self, vectors, ids: np.ndarray):
        self.ids, self.rows = ids, np.asarray(vectors[ids], dtype=np.float32)

    def __getitem__(self, wanted: np.ndarray) -> np.ndarray:
        return self.rows[np.searchsorted(self.ids, wanted)]


class _RecentRow(SequenceRow):
    """One recent frame of :class:`IndexedCandidates` as a row of the sequence scorer: the
    similarity to a place computed from the vectors (or, for a rough ranking, the one the index
    returned), neutral where a gate marked the place or the frame uninformative, and padding
    just before each end's segment."""

    def __init__(
        self, recent: tuple, vectors: np.ndarray, informative: np.ndarray, first: np.ndarray, pad: int, exact: bool
    ):
        self.frame, self.ids, self.neutral, self.places_then, self.frame_informative, self.sims, offsets = recent
        self.vectors, self.informative, self.first, self.pad, self.exact = vectors, informative, first, pad, exact
        #: (segment starts, the frame's level against each), or None: one segment
        self.offsets = offsets

    def relative(self, values: np.ndarray, places: np.ndarray) -> np.ndarray:
        """The frame's similarities to ``places`` relative to their segments' levels."""
        return values if self.offsets is None else relative_to_segments(values, places, *self.offsets)

    def values(self, places: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        first = self.first[None, :]
        inside = (places >= first) & (places < self.places_then)
        padded = (places < first) & (places >= first - self.pad)
        values = np.full(places.shape, self.neutral)
        if inside.any() and self.frame_informative and self.exact:
            needed, where = np.unique(places[inside], return_inverse=True)
            found = self.relative(self.vectors[needed] @ self.frame, needed)
            values[inside] = np.where(self.informative[needed], found, self.neutral)[where]
        elif inside.any() and self.frame_informative and len(self.ids):
            wanted = places[inside]
            at = np.minimum(np.searchsorted(self.ids, wanted), len(self.ids) - 1)
            hit = (self.ids[at] == wanted) & self.informative[wanted]
            values[inside] = np.where(hit, self.relative(self.sims[at], wanted), self.neutral)
        return values, inside | padded
