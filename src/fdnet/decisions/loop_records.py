"""What a loop-closure run records: each frame's decision (:class:`FrameDecision`), each accepted
closure (:class:`Closure`, the events' columns)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

#: columns of the events CSV, in order (the JSON lines carry the same keys)
EVENT_COLUMNS = (
    "query_index",
    "query",
    "match_index",
    "match",
    "score",
    "similarity",
    "rule",
    "threshold",
    "timestamp",
    "match_timestamp",
    "x",
    "y",
    "match_x",
    "match_y",
    "p_correct",
)


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
