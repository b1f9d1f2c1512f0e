"""The torch threads a frame is described on: chosen by measuring, on a clock the tests drive."""

import numpy as np
import pytest
import torch

from fdnet.decisions.loop_closure import LoopClosureDetector
from fdnet.decisions.loop_threads import FrameThreads
from fdnet.descriptors.classic import RawThumbnail
from fdnet.errors import ConfigError


def drive(chooser: FrameThreads, seconds_on, frames: int) -> list[int]:
    """``frames`` frames through ``chooser.run`` on a clock that advances ``seconds_on(count)``
    while a frame is described on ``count`` threads; the counts used, frame by frame."""
    now, used = [0.0], []

    def clock():
        return now[0]

    def describe():
        count = torch.get_num_threads()
        used.append(count)
        now[0] += seconds_on(count)

    chooser.clock = clock
    for _ in range(frames):
        chooser.run(describe)
    return used


def test_it_moves_to_the_count_that_describes_faster_and_back_when_that_changes():
    chooser = FrameThreads(own=2)
    used = drive(chooser, {1: 0.010, 2: 0.007}.get, 40)
    assert used[0] == 1 and chooser.current == 2 and chooser.used == {1: used.count(1), 2: used.count(2)}
    assert used[-10:].count(2) >= 8  # one frame in FIRST_EVERY probes one thread
    # the cores get loaded: two threads stall, one does not
    used = drive(chooser, {1: 0.011, 2: 0.150}.get, 60)
    assert chooser.current == 1 and used[-20:].count(1) >= 17  # probes spaced 4, 8, 16 frames apart


def test_a_probe_that_loses_spaces_the_next_further_up_to_a_limit():
    chooser = FrameThreads(own=2)
    used = drive(chooser, {1: 0.010, 2: 0.100}.get, 2000)
    assert chooser.current == 1 and chooser.every == FrameThreads.MAX_EVERY
    probes = [i for i, count in enumerate(used) if count == 2]
    gaps = np.diff(probes)
    assert (np.diff(gaps) >= 0).all() and gaps[-1] == FrameThreads.MAX_EVERY
    assert len(probes) < 20  # a loaded machine pays a stalled frame rarely


def test_a_fixed_count_or_one_own_thread_never_probes():
    assert set(drive(FrameThreads(fixed=1, own=2), {1: 0.010, 2: 0.001}.get, 50)) == {1}
    assert set(drive(FrameThreads(fixed=2, own=1), {1: 0.001, 2: 0.010}.get, 50)) == {2}
    assert set(drive(FrameThreads(own=1), {1: 0.010, 2: 0.001}.get, 50)) == {1}


def test_torch_threads_are_restored_after_the_frame():
    before = torch.get_num_threads()
    other = 1 if before != 1 else 2
    seen = []
    FrameThreads(fixed=other).run(lambda: seen.append(torch.get_num_threads()))
    assert seen == [other] and torch.get_num_threads() == before


class ThreadsSeen(RawThumbnail):
    """A descriptor that records torch's thread count while it describes."""

    seen: list

    def describe(self, images):
        self.seen.append(torch.get_num_threads())
        return super().describe(images)


def test_the_detector_describes_a_frame_on_the_setting_s_thread_count(tmp_path):
    descriptor = ThreadsSeen()
    descriptor.seen = []
    with LoopClosureDetector(
        descriptor, tmp_path / "map.db", rule="margin", threshold=0.5, frame_threads=2
    ) as detector:
        detector.describe(np.zeros((8, 8, 3), np.uint8))
        assert detector.frame_threads.used == {2: 1}
    assert descriptor.seen == [2]
    with pytest.raises(ConfigError, match="frame-threads must be a whole number of at least 1"):
        LoopClosureDetector(descriptor, tmp_path / "other.db", rule="margin", threshold=0.5, frame_threads=0)
