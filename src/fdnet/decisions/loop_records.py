"""What a loop-closure run records: each frame's decision (:class:`FrameDecision`), each accepted
closure (:class:`Closure`, the events' columns), and the growing arrays the detector keeps its map in."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


#: columns of the events CSV, in order (the JSON lines carry the same keys)
EVENT_COLUMNS = ("query_index", "query", "match_index", "match", "score", "similarity", "rule", "threshold",
                 "timestamp", "match_timestamp", "x", "y", "match_x", "match_y", "p_correct")


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
    #: planar position in metres of the frame and of the place it closes with, when frames carry
    #: positions (a bag's GPS or odometry, the Python API's ``position=``)
    x: float | None = None
    y: float | None = None
    match_x: float | None = None
    match_y: float | None = None
    #: the probability that the closure is right, from the calibration's fit of it against the
    #: score (None when the threshold came without one)
    p_correct: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class FrameDecision:
    """What the detector decided for one frame, accepted or not (for evaluation): the candidate
    its rule vouches for (``match`` -1 when there was none: nothing searchable yet, or the frame
    was gated), the acceptance ``score`` (NaN when nothing was searchable; -inf when a gate
    rejected it) and how many places were searchable (the places the frame could have matched:
    indices 0..searchable-1)."""

    query_index: int
    match: int
    score: float
    accepted: bool
    searchable: int
    #: the best place by (sequence) similarity and that similarity (the ranking, for Recall@1)
    best: int = -1
    best_similarity: float = float("nan")
    #: why the frame could not close a loop whatever its score: "uninformative" (dark, blank),
    #: "still" (the robot has not moved since its previous frame), "no informative place" (no
    #: searchable place can be a candidate), "" otherwise
    gated: str = ""
    #: the rule's score before the consistency gate (equal to ``score`` without the gate)
    rule_score: float = float("nan")


class GrowingArray:
    """The database's vectors in memory, appended a row at a time (capacity doubles, so adding
    N rows copies O(N) rows in all, where np.vstack per frame would copy O(N^2)). With ``dim``
    None it holds one value per place (bool unless ``dtype`` says otherwise)."""

    def __init__(self, dim: int | None, initial: np.ndarray | None = None, dtype=None):
        dtype = dtype if dtype is not None else bool if dim is None else np.float32
        shape = () if dim is None else (dim,)
        rows = np.zeros((0, *shape), dtype) if initial is None else np.asarray(initial, dtype)
        self._data = np.empty((max(1024, 2 * len(rows)), *shape), dtype=dtype)
        self._data[:len(rows)] = rows
        self._count = len(rows)

    def __len__(self) -> int:
        return self._count

    def append(self, row: np.ndarray) -> None:
        if self._count == len(self._data):
            grown = np.empty((2 * len(self._data), *self._data.shape[1:]), dtype=self._data.dtype)
            grown[:self._count] = self._data[:self._count]
            self._data = grown
        self._data[self._count] = row
        self._count += 1

    def truncate(self, count: int) -> None:
        """Forget the rows from ``count`` on."""
        self._count = min(int(count), self._count)

    def view(self, count: int | None = None) -> np.ndarray:
        return self._data[:self._count if count is None else count]
