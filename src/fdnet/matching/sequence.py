"""SeqSLAM-style sequence matching over any method's similarity matrix.

Milford & Wyeth, "SeqSLAM: Visual route-based navigation for sunny summer days and stormy
winter nights", ICRA 2012. A query is matched not alone but as the last frame of a sequence of
``length`` consecutive queries: each reference ``r`` is scored by the mean similarity along
straight lines through the (query x reference) matrix that end at ``(q, r)`` with slopes
(reference frames per query frame) in ``velocities``. Works on any similarity (cosine, negative
SAD...), so every descriptor gains sequence matching for free.

Hand-written because no maintained library implements it over an arbitrary matrix; the core is
vectorised over references and velocities (one gather per sequence step).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

#: slopes (reference frames per query frame) SeqSLAM tries by default
DEFAULT_VELOCITIES = (0.8, 0.9, 1.0, 1.1, 1.25)


def sequence_reach(length: int, velocities=DEFAULT_VELOCITIES) -> int:
    """How many places before its end a sequence of ``length`` frames can reach at the fastest
    velocity (0 for single images): the neutral padding a map segment needs so that no sequence
    runs into the segment before it."""
    return int(math.ceil(max(velocities) * (length - 1))) if length > 1 else 0


def check_sequence_length(value, where: str = "--sequence-length") -> int:
    """``value`` as a sequence length: a whole number of frames, at least 1 (1 = single images,
    everywhere: matching, evaluation, calibration and loop closure)."""
    from fdnet.errors import ConfigError

    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ConfigError(f"{where} must be a whole number of frames, at least 1 (1 = single images), got {value!r}")
    return int(value)


def enhance_contrast(similarity: np.ndarray, window: int = 10) -> np.ndarray:
    """SeqSLAM's local contrast enhancement: normalise each entry by the mean and std of the
    ``window`` references around it in the same query row (column-wise in the original's
    difference-matrix orientation). Makes rows from different conditions comparable."""
    s = np.asarray(similarity, dtype=np.float64)
    if window <= 1:
        return s.astype(np.float32)
    # Sliding mean/std along the reference axis via cumulative sums (O(QR)).
    pad = window // 2
    padded = np.pad(s, ((0, 0), (pad, pad)), mode="edge")
    c1 = np.cumsum(np.pad(padded, ((0, 0), (1, 0))), axis=1)
    c2 = np.cumsum(np.pad(padded**2, ((0, 0), (1, 0))), axis=1)
    n = 2 * pad + 1
    mean = (c1[:, n:] - c1[:, :-n]) / n
    var = np.maximum((c2[:, n:] - c2[:, :-n]) / n - mean**2, 0.0)
    mean, var = mean[:, : s.shape[1]], var[:, : s.shape[1]]
    return ((s - mean) / (np.sqrt(var) + 1e-6)).astype(np.float32)


def sequence_similarity(
    similarity: np.ndarray,
    length: int = 10,
    velocities: tuple[float, ...] | np.ndarray = DEFAULT_VELOCITIES,
    contrast_window: int = 0,
) -> np.ndarray:
    """(Q, R) single-image similarity -> (Q, R) sequence similarity (higher = better).

    Entry (q, r) is the best, over velocities v, of the mean of
    ``similarity[q - k, round(r - k * v)]`` for k = 0..length-1 (the sequence ends at q, r).
    At the start of the query traverse the sequence is shortened to the frames available;
    reference indices that fall off the map are ignored in the mean. Each row is
    :func:`online_sequence_scores` over the rows up to it: one scorer, offline and online.
    """
    s = np.asarray(similarity, dtype=np.float32)
    if contrast_window:
        s = enhance_contrast(s, contrast_window)
    if length <= 1:
        return s.copy()
    best = np.empty(s.shape, dtype=np.float32)
    for q in range(len(s)):
        best[q] = online_sequence_scores(s[max(0, q - length + 1) : q + 1], velocities=velocities)
    return best


def sequence_top_k(
    queries: np.ndarray,
    references: np.ndarray,
    k: int,
    length: int = 10,
    similarity=None,
    velocities: tuple[float, ...] | np.ndarray = DEFAULT_VELOCITIES,
    contrast_window: int = 0,
    max_entries: int = 16_000_000,
) -> tuple[np.ndarray, np.ndarray]:
    """Best ``k`` references per query by sequence similarity, without the (Q, R) matrix.

    The same numbers as ``top_k_of_matrix(sequence_similarity(similarity_matrix(...)), k)``:
    each query's row depends only on the single-image similarity rows of the ``length - 1``
    queries before it, so blocks of query rows are computed with that many rows of overlap and
    reduced to their top ``k`` at once. Memory: about ``max_entries`` similarity values.
    """
    from fdnet.matching.similarity import dot_similarity, top_k_of_matrix

    fn = similarity or dot_similarity
    q = np.asarray(queries)
    r = np.asarray(references)
    num_q, num_r = len(q), len(r)
    k = int(min(max(k, 1), num_r))
    overlap = max(int(length), 1) - 1
    block = max(1, int(max_entries) // max(num_r, 1) - overlap)
    best_idx = np.zeros((num_q, k), dtype=np.int64)
    best_score = np.zeros((num_q, k), dtype=np.float32)
    for start in range(0, num_q, block):
        first = max(0, start - overlap)
        rows = np.asarray(fn(q[first : start + block], r), dtype=np.float32)
        seq = sequence_similarity(rows, length, velocities, contrast_window)[start - first :]
        idx, scores = top_k_of_matrix(seq, k)
        best_idx[start : start + len(seq)] = idx
        best_score[start : start + len(seq)] = scores
    return best_idx, best_score


class SequenceRow:
    """A frame's similarities to chosen places only (a search that does not score every place):
    :meth:`values` gives, for an array of place ids, (the similarities, which of them count in
    the mean). Subclasses say how they are read; :func:`online_sequence_scores` does the rest."""

    def values(self, places: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(similarity, counted) for ``places`` (shape (velocities, ends)); ``end`` holds the
        sequence end of each column, for rows whose reading depends on it."""
        raise NotImplementedError


def sequence_places(ends: np.ndarray, k: int, velocities: np.ndarray) -> np.ndarray:
    """(velocities, ends) place ids that the frame ``k`` steps back reads in the sums of the
    sequences ending at ``ends``: ``round(end - k x v)`` for each velocity ``v``."""
    return np.rint(ends[None, :] - k * velocities[:, None]).astype(np.int64)


def online_sequence_scores(
    rows: Sequence[np.ndarray | SequenceRow],
    searchable: int | None = None,
    velocities: tuple[float, ...] | np.ndarray = DEFAULT_VELOCITIES,
    ends: np.ndarray | None = None,
    exact_sums: bool = False,
) -> np.ndarray:
    """Sequence similarity of the newest frame of a robot's traverse, from the frames seen so
    far: the one sequence scorer (the matrix version, loop closure and its indexed search all
    call it).

    ``rows[-1]`` is the newest frame's single-image similarity to the map's places, ``rows[-1 - k]``
    that of the frame ``k`` steps earlier (oldest first; the sequence length is ``len(rows)``).
    A row may be shorter than the newest one: the map grew since that frame was seen, and the
    places added later are simply not in it. Entry ``r`` (for the first ``searchable`` places,
    default all of the newest row, or for the place ids ``ends``) is the best, over velocities
    ``v``, of the mean of ``rows[-1 - k][round(r - k * v)]`` over the ``k`` whose index falls
    inside that row. With rows of one length this is the last row of :func:`sequence_similarity`
    over the same frames, computed without the others: causal, since it reads only
    similarities of frames already seen. A row may also be a :class:`SequenceRow` (with
    ``ends``): a frame whose similarities are read only where the sum needs them.
    ``exact_sums``: return the float64 means (a search ranking many ends keeps their order)
    instead of float32 scores.
    """
    if not len(rows):
        raise ValueError("online_sequence_scores needs at least the newest frame's row")
    v = np.asarray(velocities, dtype=np.float64)
    if ends is None:
        newest = np.asarray(rows[-1], dtype=np.float32)
        count = len(newest) if searchable is None else int(searchable)
        if count > len(newest) or count < 0:
            raise ValueError(f"searchable={count} is outside the newest row of {len(newest)} places")
        refs = np.arange(count)
    else:
        refs = np.asarray(ends, dtype=np.int64)
        count = len(refs)
    total = np.zeros((len(v), count), dtype=np.float64)
    valid_count = np.zeros((len(v), count), dtype=np.float64)
    for k in range(len(rows)):
        row = rows[-1 - k]
        if isinstance(row, SequenceRow):
            values, counted = row.values(sequence_places(refs, k, v), refs)
            total += np.where(counted, values, 0.0)
            valid_count += counted
            continue
        row = np.asarray(row, dtype=np.float32)
        if not len(row):
            continue
        for i, velocity in enumerate(v):
            step = k * velocity
            if ends is None and abs(step - np.floor(step) - 0.5) > 1e-9:
                # round(r - step) = r - round(step) for whole r when step is no half-way case: one
                # shifted slice (a copy) instead of a gather
                shift = int(np.rint(step))
                lo, hi = max(shift, 0), min(count, len(row) + shift)
                if lo < hi:
                    total[i, lo:hi] += row[lo - shift : hi - shift]
                    valid_count[i, lo:hi] += 1
                continue
            # half-way: np.rint rounds r - step to even, which depends on r, so gather
            cols = np.rint(refs - step).astype(np.int64)
            valid = (cols >= 0) & (cols < len(row))
            total[i] += np.where(valid, row[np.clip(cols, 0, len(row) - 1)], 0.0)
            valid_count[i] += valid
    mean = np.where(valid_count > 0, total / np.maximum(valid_count, 1), -np.inf)
    best = mean.max(axis=0) if count else np.zeros(0)
    return best if exact_sums else best.astype(np.float32)
