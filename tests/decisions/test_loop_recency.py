"""The robot's recent past found from the traverse itself, and seams between recordings."""

import math

import numpy as np
import pytest

from fdnet.data.groundtruth import GroundTruth
from fdnet.decisions.loop_closure import LoopClosureDetector
from fdnet.decisions.loop_evaluation import evaluate_decisions
from fdnet.decisions.loop_gates import LoopGates
from fdnet.decisions.loop_recency import (
    LEVEL_PLACES,
    NULL_QUANTILE,
    GapDetector,
    Seams,
    relative_to_segments,
    segment_levels,
    similar_past,
    walk_back,
)
from fdnet.performance.loop_benchmark import StoredVectors


def unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def slow_route(n=200, dim=64, persistence=0.93, seed=0):
    """A robot slow for its frame rate: its view drifts as an AR(1) process, so a frame resembles
    the frames 10 back (0.43) and 20 back (0.21) more than unrelated places (0.0); then the same
    route again under another condition (noise). Returns (first pass, second pass)."""
    rng = np.random.default_rng(seed)
    state = np.zeros((n, dim))
    state[0] = rng.normal(size=dim)
    for t in range(1, n):
        state[t] = persistence * state[t - 1] + math.sqrt(1 - persistence**2) * rng.normal(size=dim)
    return unit(state + 0.3 * rng.normal(size=(n, dim))), unit(state + 0.5 * rng.normal(size=(n, dim)))


def drive(first, second, **settings):
    detector = LoopClosureDetector(
        StoredVectors(first.shape[1]), rule="margin", threshold=math.inf, sequence_length=10, **settings
    )
    for i, vector in enumerate(np.concatenate([first, second])):
        detector.process_vector(vector, name=f"frame_{i}", new_segment=i == len(first))
    return detector


def revisit_truth(n):
    return GroundTruth([np.zeros(0, np.int64)] * n + [np.arange(max(i - 1, 0), min(i + 2, n)) for i in range(n)], 2 * n)


def test_walk_back_passes_frames_above_the_level_and_stops_after_patience_below():
    back = np.array([0.9, 0.8, 0.2, 0.7, 0.6, 0.1, 0.1, 0.1, 0.1, 0.1, 0.9])
    assert walk_back(back, 0.5, patience=1) == 2
    assert walk_back(back, 0.5, patience=2) == 5  # one frame below is noise
    assert walk_back(back, 0.5, patience=5) == 5  # the far 0.9 is after 5 below: not reached
    assert walk_back(back, 0.95, patience=2) == 0
    assert walk_back(np.zeros(0), 0.5) == 0


def test_similar_past_reaches_through_a_slow_decay_but_not_a_revisit_beyond_it():
    rng = np.random.default_rng(0)
    row = rng.normal(0.2, 0.03, size=400)  # unrelated places
    row[10] = 0.8  # a revisit, long ago
    recent = np.arange(399, 299, -1)  # the segment's frames, newest first
    row[recent[:25]] = np.linspace(0.9, 0.35, 25)  # the recent past fades over 25 frames
    reach = similar_past(row, recent)
    assert 25 <= reach <= 35  # the whole fade, and at most a few unrelated frames after it
    # a frame whose previous frames are already unlike it excludes nothing
    row[recent[:25]] = 0.2
    assert similar_past(row, recent) <= 2


def test_a_slow_robot_closes_no_loop_with_its_recent_past_and_needs_no_frame_count():
    """A frame count too small for the robot's speed lets the frames just outside it win (their
    similarity still falls with every frame back, so they stand out from the rest): the
    default finds how far back the robot still sees the same place."""
    first, second = slow_route()
    truth = revisit_truth(len(first))
    by_count = drive(first, second, exclude_last=5, gates=LoopGates(similar_past=False))
    default = drive(first, second)
    recall = {
        name: evaluate_decisions(d.decisions, truth, math.inf, "margin")["metrics"]["recall_at_100_precision"]
        for name, d in (("count", by_count), ("default", default))
    }
    assert recall["default"] >= 0.9 > 0.8 >= recall["count"]
    # the first pass's best score is below the revisits' median: no first-pass closure survives
    first_pass = max(d.score for d in default.decisions[: len(first)] if math.isfinite(d.score))
    revisits = np.median([d.score for d in default.decisions[len(first) :] if math.isfinite(d.score)])
    assert first_pass < revisits
    assert np.median(default.excluded_back[: len(first)]) >= 20


def test_seams_lay_each_segment_after_its_own_padding():
    seams = Seams(pad=3)
    for new in (True, False, False, True, False):
        seams.add(new)
    assert list(seams.columns()) == [3, 4, 5, 9, 10] and list(seams.columns(4)) == [3, 4, 5, 9]
    assert [seams.width(n) for n in range(6)] == [0, 4, 5, 6, 10, 11]
    assert seams.segments == 2 and list(seams.first_places(np.array([4, 2, 3]))) == [3, 0, 3]
    assert list(seams.padded(np.array([1.0, 2, 3, 4, 5]), 0.5)) == [0.5, 0.5, 0.5, 1, 2, 3, 0.5, 0.5, 0.5, 4, 5]
    seams.truncate(3)
    assert seams.segments == 1 and len(seams) == 3


def test_no_sequence_spans_the_start_of_a_new_pass():
    """The second pass decides only once it has a whole sequence of its own, and its scores are
    those it would get if the first pass had been recorded in an earlier session."""
    first, second = slow_route(n=80)
    one_run = drive(first, second)
    gated = [d.gated for d in one_run.decisions[80:89]]
    assert gated == ["incomplete sequence"] * 9 and one_run.decisions[89].gated == ""
    assert one_run.segments == 2
    # the first pass stored by an earlier session: the second pass's decisions are the same
    earlier = LoopClosureDetector(StoredVectors(64), rule="margin", threshold=math.inf, sequence_length=10)
    for i, vector in enumerate(first):
        earlier.process_vector(vector, name=f"frame_{i}")
    later = LoopClosureDetector(
        StoredVectors(64), earlier.database, rule="margin", threshold=math.inf, sequence_length=10
    )
    for i, vector in enumerate(second):
        later.process_vector(vector, name=f"frame_{80 + i}")
    assert [(d.match, d.score) for d in later.decisions] == [(d.match, d.score) for d in one_run.decisions[80:]]


def test_a_gap_in_time_starts_a_new_segment():
    gaps = GapDetector()
    times = [0.0, 0.1, 0.2, 0.3, 0.4, 9.0, 9.1]
    assert [gaps.gap(t) for t in times] == [False, False, False, False, False, True, False]
    first, _ = slow_route(n=20)
    detector = LoopClosureDetector(StoredVectors(64), rule="margin", threshold=math.inf, sequence_length=3)
    for i, vector in enumerate(first):
        detector.process_vector(vector, name=f"f{i}", timestamp=0.1 * i + (60.0 if i >= 12 else 0.0))
    assert detector.segments == 2
    assert [d.gated for d in detector.decisions[12:14]] == ["incomplete sequence"] * 2


@pytest.mark.parametrize("stop", [85, 95])
def test_a_resumed_run_replays_its_segments(tmp_path, stop):
    first, second = slow_route(n=80)
    whole = drive(first, second)
    frames = np.concatenate([first, second])
    detector = LoopClosureDetector(
        StoredVectors(64), tmp_path / "map.db", rule="margin", threshold=math.inf, sequence_length=10
    )
    with detector:
        for i in range(stop):
            detector.process_vector(frames[i], name=f"frame_{i}", new_segment=i == 80)
    with LoopClosureDetector(
        StoredVectors(64), tmp_path / "map.db", rule="margin", threshold=math.inf, sequence_length=10
    ) as resumed:
        resumed.resume(stop)
        for i in range(stop, len(frames)):
            resumed.process_vector(frames[i], name=f"frame_{i}", new_segment=i == 80)
        assert list(map(repr, resumed.decisions)) == list(map(repr, whole.decisions))
        assert resumed.excluded_back == whole.excluded_back


def test_segment_levels_put_each_segment_on_its_own_scale():
    rng = np.random.default_rng(0)
    low, high = rng.normal(0.1, 0.05, 60), rng.normal(0.5, 0.05, 50)
    small = rng.normal(0.9, 0.05, LEVEL_PLACES - 1)
    row = np.concatenate([low, high, small]).astype(np.float32)
    places, starts = np.arange(len(row)), np.array([0, 60, 110])
    levels = segment_levels(row, places, starts)
    assert levels[0] == pytest.approx(np.quantile(low, NULL_QUANTILE))
    assert levels[1] == pytest.approx(np.quantile(high, NULL_QUANTILE))
    assert levels[2] == pytest.approx(np.quantile(row, NULL_QUANTILE))  # too few places: the level of all
    relative = relative_to_segments(row, places, starts, levels)
    assert relative.dtype == np.float32
    np.testing.assert_allclose(relative[60:110], high - levels[1], atol=1e-6)
    # many segments of any size, in any order of places: each its own quantile, as numpy's
    many = rng.normal(size=3000)
    places = rng.permutation(3000)
    starts = np.r_[0, np.sort(rng.choice(np.arange(1, 3000), 99, replace=False))]
    levels = segment_levels(many, places, starts)
    segment = np.searchsorted(starts, places, side="right") - 1
    for k in range(len(starts)):
        inside = many[segment == k]
        expected = (
            np.quantile(inside, NULL_QUANTILE) if len(inside) >= LEVEL_PLACES else np.quantile(many, NULL_QUANTILE)
        )
        assert levels[k] == pytest.approx(expected)
    # one segment: nothing to put on one scale, the similarities stay as they are
    assert segment_levels(row, places, np.array([0])) is None
    assert relative_to_segments(row, places, np.array([0]), None) is row


@pytest.mark.parametrize("search", ["exact", "index"])
def test_a_second_pass_does_not_close_with_its_own_look_alikes(search):
    """The second pass's frames share its conditions, so each resembles the pass's own earlier
    (unrelated) frames more than its revisited place in the first pass; scored against each
    recording's own level, every revisit closes with its place."""
    dim, first, new, back = 64, 60, 50, 20
    rng = np.random.default_rng(1)
    content = rng.normal(size=(first + new, dim))
    summer, winter = rng.normal(size=dim), rng.normal(size=dim)
    first_pass = unit(content[:first] + summer)
    second_pass = unit(
        np.concatenate([content[first:] + winter, content[:back] + winter + 0.3 * rng.normal(size=(back, dim))])
    )
    revisits = second_pass[new:]
    # the premise: by raw similarity, a revisit's best searchable place is mostly in its own pass
    own = revisits @ second_pass[: new - 3].T
    assert (own.max(axis=1) > (revisits * first_pass[:back]).sum(axis=1)).sum() >= back * 3 // 4
    settings = dict(exclude_last=3, rule="raw", threshold=math.inf, gates=LoopGates(similar_past=False))
    with LoopClosureDetector(StoredVectors(dim), search=search, **settings) as detector:
        for i, v in enumerate(np.concatenate([first_pass, second_pass])):
            detector.process_vector(v, name=f"f{i}", new_segment=i == first)
    assert [d.match for d in detector.decisions[first + new :]] == list(range(back))
