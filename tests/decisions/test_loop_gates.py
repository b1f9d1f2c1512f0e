"""The loop gates on their own: settings, the pixel signals, the robot's recent past and the
consistency gate, each on hand-made inputs."""

import math

import numpy as np
import pytest

from fdnet.decisions.loop_gates import (
    ConsistencyGate,
    LoopGates,
    RecentPast,
    frame_signals,
    informative_frames,
    is_still,
)
from fdnet.errors import ConfigError


def test_settings_are_checked_and_parsed():
    assert LoopGates().with_settings(["consistency=3", "still_difference=off", "exclude-seconds=2.5"]) == LoopGates(
        consistency=3, still_difference=None, exclude_seconds=2.5
    )
    assert LoopGates().with_settings(["decide_when_still=true"]).decide_when_still is True
    for bad, message in (
        (["min_brightness=2"], "must be in [0, 1]"),
        (["consistency=0"], "at least 1"),
        (["consistency=x"], "not a number"),
        (["nosuch=1"], "unknown loop gate setting"),
        (["exclude_metres=-1"], "at least 0"),
        (["consistency"], "expected KEY=VALUE"),
        (["decide_when_still=maybe"], "true or false"),
        (["consistency=2.5"], "give a whole number of frames"),
        (["consistency_window=inf"], "give a whole number of frames"),
    ):
        with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
            LoopGates().with_settings(bad)
    with pytest.raises(ConfigError, match="unknown loop gate"):
        LoopGates.from_dict({"colour": 1})
    # a number written with an exponent is a number of frames, not "not a number"
    assert LoopGates().with_settings(["consistency=1e3"]).consistency == 1000


def test_signals_find_dark_and_blank_frames_whatever_the_dtype():
    rng = np.random.default_rng(0)
    textured = rng.integers(0, 256, size=(48, 64, 3)).astype(np.uint8)
    dark = (textured // 20).astype(np.uint8)  # mean about 6 of 255: a tunnel
    blank = np.full((48, 64, 3), 140, np.uint8)  # a covered lens or a white wall
    frames = np.stack([textured, dark, blank])
    for images in (frames, frames.astype(np.float32) / 255.0):
        signals = frame_signals(images)
        assert signals.thumbnails.shape == (3, 16, 32) and len(signals) == 3
        assert informative_frames(signals.statistics, LoopGates()).tolist() == [True, False, False]
        off = LoopGates(min_brightness=None, min_contrast=None)
        assert informative_frames(signals.statistics, off).tolist() == [True, True, True]
    still = frame_signals(np.stack([textured, np.clip(textured.astype(int) + 2, 0, 255).astype(np.uint8)]))
    assert is_still(still.thumbnails[1], still.thumbnails[0], LoopGates())
    assert not is_still(still.thumbnails[1], still.thumbnails[0], LoopGates(still_difference=None))
    moved = frame_signals(np.stack([textured, np.roll(textured, 8, axis=1)]))
    assert not is_still(moved.thumbnails[1], moved.thumbnails[0], LoopGates())


def test_the_recent_past_grows_back_over_a_stop_and_over_seconds_and_metres():
    recent = RecentPast(exclude_last=2, gates=LoopGates())
    still = [False, False, False, True, True, True, False, False]  # the robot stands at frames 2..5
    firsts = [recent.first_excluded(t, None, s, None, None) for t, s in enumerate(still)]
    # moving: the last two frames; standing: back to the stop's first frame (2)
    assert firsts == [0, 0, 0, 1, 2, 2, 4, 5]
    timed = RecentPast(exclude_last=1, gates=LoopGates(exclude_seconds=1.0, still_difference=None))
    times = [0.0, 0.5, 1.0, 1.2, 3.0]
    # the last second, or the last frame (exclude_last), whichever reaches further back
    assert [timed.first_excluded(t, None, False, s, None) for t, s in enumerate(times)] == [0, 0, 0, 1, 3]
    walked = RecentPast(exclude_last=0, gates=LoopGates(exclude_metres=5.0, still_difference=None))
    xy = [(0, 0), (3, 0), (6, 0), (6, 4), (20, 0)]
    assert [walked.first_excluded(t, None, False, None, p) for t, p in enumerate(xy)] == [0, 0, 1, 2, 4]
    by_similarity = RecentPast(exclude_last=1, gates=LoopGates(segment_similarity=0.9, still_difference=None))
    sims = [None, 0.5, 0.95, 0.97, 0.2]
    assert [by_similarity.first_excluded(t, s, False, None, None) for t, s in enumerate(sims)] == [0, 0, 1, 1, 3]


def test_consistency_gate_on_hand_made_decisions():
    gate = ConsistencyGate(k=3, window=2)
    # (match, score) per frame: three agreeing frames, then a jump, then agreement again
    frames = [(10, 0.5), (11, 0.6), (12, 0.4), (40, 0.9), (41, 0.8), (43, 0.7), (-1, math.nan), (44, 0.9)]
    gated = [gate.update(m, s) for m, s in frames]
    assert gated[:2] == [-math.inf, -math.inf]  # not yet k frames
    assert gated[2] == 0.4  # the smallest of the three
    assert gated[3] == gated[4] == -math.inf  # 12 -> 40 breaks the chain, and it is still in the window
    assert gated[5] == 0.7  # 40, 41, 43: steps of 1 and 2
    assert gated[6] == gated[7] == -math.inf  # a frame without a candidate breaks it too
    single = ConsistencyGate(k=1, window=0)
    assert single.update(5, 0.3) == 0.3 and single.update(-1, math.nan) == -math.inf
    backwards = ConsistencyGate(k=2, window=1)
    assert backwards.update(9, 0.5) == -math.inf and backwards.update(8, 0.6) == 0.5  # a route driven backwards
