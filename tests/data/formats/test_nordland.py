"""Nordland: per-season folders (frames aligned by the number in their names) and the partitioned
release (train/test, sections)."""

import numpy as np
import pytest

from fdnet.data.formats import detect_format, open_split, open_training
from fdnet.errors import DataError

from .conftest import write_frames
from conftest import require_shared


def make_trimmed(root, n=12, step=10, seasons=("summer", "winter")):
    """Like ../shared/data/nordland_trimmed: every 10th frame of the 1 fps sequence."""
    for season in seasons:
        write_frames(root / season, [f"images-{(i + 1) * step:05d}.png" for i in range(n)])
    return root


def test_per_season_frames_align_by_number(tmp_path):
    root = make_trimmed(tmp_path / "nordland")
    # winter misses frame 30: alignment by number must not shift the rest
    (root / "winter" / "images-00030.png").unlink()
    assert detect_format(root) == "nordland"
    split = open_split(root, split="all", filter_frames=False)
    assert (split.reference.name, split.query.name) == ("summer", "winter")
    assert len(split.query) == 11 and len(split.reference) == 11  # the split keeps common frames
    assert all(p.tolist() == [i] for i, p in enumerate(split.ground_truth.positives))
    # tolerance 5 frames of the 1 fps sequence < one 10-frame step: exact matches only
    assert split.ground_truth.summary()["mean_matches_per_query"] == 1.0
    wide = open_split(root, split="all", filter_frames=False, tolerance=10)
    assert wide.ground_truth.positives[3].tolist() == [2, 3, 4]
    # and the description says so, instead of a bare "tolerance 5 frames"
    assert "tolerance 5 frames of the 1 fps sequence = 0 of these files (10 frames apart)" in split.description
    assert "= 1 of these files" in wide.description


def test_named_splits(tmp_path, monkeypatch):
    import fdnet.data.formats.nordland as nordland

    monkeypatch.setattr(nordland, "TEST_FRAMES", 4)
    monkeypatch.setitem(nordland.SPLITS, "test", lambda n: (max(n - 4, 0), None))
    monkeypatch.setitem(nordland.SPLITS, "train", lambda n: (0, max(n - 4, 0)))
    root = make_trimmed(tmp_path / "nordland", seasons=("spring", "summer", "fall", "winter"))
    test = open_split(root, filter_frames=False)  # default split: test
    assert test.query.frame_ids.tolist() == [90, 100, 110, 120]
    train = open_training(root, filter_frames=False)
    assert train.conditions == ["spring", "summer", "fall", "winter"]
    assert train["fall"].frame_ids.tolist() == [10, 20, 30, 40, 50, 60, 70, 80]


def test_decorated_season_folder_names(tmp_path):
    for season in ("nordland_summer_images", "nordland_winter_images"):
        write_frames(tmp_path / season / "images", [f"{i}.png" for i in range(1, 4)])
    split = open_split(tmp_path, split="all", filter_frames=False)
    assert split.reference.name == "summer" and split.query.frame_ids.tolist() == [1, 2, 3]


def make_partitioned(root):
    for part, sections in (
        ("train", {"section1": range(1, 6)}),
        ("test", {"section1": range(100, 103), "section2": range(200, 202)}),
    ):
        for season in ("summer", "winter"):
            for section, numbers in sections.items():
                write_frames(root / part / f"{season}_images_{part}" / section, [f"{n}.png" for n in numbers])
    return root


def test_partitioned_release(tmp_path):
    root = make_partitioned(tmp_path / "partitioned")
    assert detect_format(root) == "nordland"
    test = open_split(root)  # test partition, no filtering (the release is already filtered)
    assert test.query.frame_ids.tolist() == [100, 101, 102, 200, 201]
    assert [p.name for p in test.query.paths][:2] == ["100.png", "101.png"]
    assert test.ground_truth.positives[4].tolist() == [3, 4]  # 201 vs 200, 201 (5-frame tolerance)
    assert test.ground_truth.positives[2].tolist() == [0, 1, 2]  # 102: never 200 in the next section
    train = open_training(root)
    assert train["summer"].frame_ids.tolist() == [1, 2, 3, 4, 5]


def test_missing_frame_numbers(tmp_path):
    write_frames(tmp_path / "summer", ["a.png", "b.png"])
    write_frames(tmp_path / "winter", ["a.png", "b.png"])
    with pytest.raises(DataError, match="carries no frame number"):
        open_split(tmp_path, dataset_format="nordland", filter_frames=False, split="all")


@pytest.mark.shared_data
def test_real_nordland_trimmed():
    root = require_shared("nordland_trimmed")
    split = open_split(root, filter_frames=False)
    assert len(split.query) == len(split.reference) == 1000  # test = last 1000 frames
    assert split.query.frame_ids[0] == 15770 and split.ground_truth.summary()["mean_matches_per_query"] == 1.0
    train = open_training(root, filter_frames=False)
    assert len(train["summer"]) == 1576 and train["winter"].frame_ids[-1] == 15760


def test_paper_filter_drops_a_frame_from_every_season(tmp_path, monkeypatch):
    """The adapter runs the one frame filter (fdnet.data.filters.filter_frames) over every season
    present, drops a position dark in any season from all of them, and caches what it kept."""
    from fdnet.data import filters
    from fdnet.data.dataset import RouteDataset

    calls = []

    def filter_route(route, *settings):
        # a tunnel in winter at frame 30 (position 2): the real detectors are tested in test_filters.py
        calls.append(sorted(route.traverses))
        kept = np.array([i for i, f in enumerate(route["winter"].frame_ids) if f != 30])
        report = filters.FilterReport(num_frames=len(route["winter"]), kept=kept, dark={"winter": np.array([2])})
        return RouteDataset(route.root, {k: t.select(kept) for k, t in route.traverses.items()}), report

    monkeypatch.setattr(filters, "filter_route", filter_route)
    root = make_trimmed(tmp_path / "nordland", n=6, seasons=("spring", "summer", "winter"))
    cache = tmp_path / "cache"
    # filter_frames defaults to on for the per-season layout; it sees every season, not just the pair
    split = open_split(root, split="all", filter_cache=str(cache))
    assert calls == [["spring", "summer", "winter"]]
    assert split.reference.frame_ids.tolist() == split.query.frame_ids.tolist() == [10, 20, 40, 50, 60]
    assert "frame filter: kept 5 of 6 frames: dropped 1 dark" in split.description
    # the kept frame numbers are cached: a second open does not run the detectors again
    again = open_split(root, reference="spring", query="winter", split="all", filter_cache=str(cache))
    assert len(calls) == 1 and again.query.frame_ids.tolist() == [10, 20, 40, 50, 60]
    assert len(list(cache.iterdir())) == 1


@pytest.mark.shared_data
def test_real_nordland_tunnels_filtered(tmp_path):
    """The real filter on a 240-frame stretch of nordland_trimmed that enters and leaves tunnels
    (links to the real files, so the test stays fast)."""
    pytest.importorskip("fdnet.data.filters")
    from fdnet.data.images import load_images, to_grey

    source = require_shared("nordland_trimmed")
    root = tmp_path / "nordland"
    for season in ("summer", "winter"):
        (root / season).mkdir(parents=True)
        for path in sorted((source / season).iterdir())[:240]:
            (root / season / path.name).symlink_to(path)
    kept = open_split(root, split="all", filter_cache=str(tmp_path / "cache"))
    assert kept.query.frame_ids.tolist() == kept.reference.frame_ids.tolist()
    assert 0 < 240 - len(kept.query) < 120, kept.description
    black = set()  # nearly black (tunnel) frames of either season
    for season in ("summer", "winter"):
        paths = sorted((root / season).iterdir())
        brightness = to_grey(load_images(paths, (16, 32))).reshape(len(paths), -1).mean(axis=1)
        black |= {int(p.stem.split("-")[1]) for p, b in zip(paths, brightness) if b < 0.03}
    assert len(black) >= 10 and not black & set(kept.query.frame_ids.tolist())
