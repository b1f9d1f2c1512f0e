"""Datasets (one folder per condition), traverses, frame ranges, and frame-aligned splits."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from fdnet.data.dataset import RouteDataset, Traverse, parse_frame_range
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.split import EvaluationSplit, aligned_split
from fdnet.errors import DataError

from conftest import require_shared


def _make(root, counts: dict[str, int]):
    for cond, n in counts.items():
        (root / cond).mkdir(parents=True)
        for i in range(n):
            Image.fromarray(np.full((4, 6, 3), i * 10, np.uint8)).save(root / cond / f"f{i:03d}.png")
    return root


def test_from_folder_finds_condition_folders_with_images(tmp_path):
    _make(tmp_path, {"summer": 3, "winter": 3})
    (tmp_path / ".cache").mkdir()
    (tmp_path / ".cache" / "x.png").write_bytes(b"x")
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "a.txt").write_text("no images here")
    ds = RouteDataset.from_folder(tmp_path)
    assert ds.conditions == ["summer", "winter"]
    assert [p.name for p in ds["winter"].paths] == ["f000.png", "f001.png", "f002.png"]
    assert list(ds["summer"].frame_ids) == [0, 1, 2]
    # Picking and ordering conditions explicitly.
    assert RouteDataset.from_folder(tmp_path, ["winter", "summer"]).conditions == ["winter", "summer"]


def test_missing_root_condition_and_empty_folders_are_clear_errors(tmp_path):
    with pytest.raises(DataError, match="dataset folder not found"):
        RouteDataset.from_folder(tmp_path / "absent")
    with pytest.raises(DataError, match="no condition sub-folders with images"):
        RouteDataset.from_folder(tmp_path)
    _make(tmp_path, {"summer": 2})
    with pytest.raises(DataError, match=r"autumn: condition folder not found; available: summer"):
        RouteDataset.from_folder(tmp_path, ["summer", "autumn"])
    (tmp_path / "winter").mkdir()
    with pytest.raises(DataError, match="winter: contains no images"):
        RouteDataset.from_folder(tmp_path, ["winter"])
    ds = RouteDataset.from_folder(tmp_path)
    with pytest.raises(DataError, match="no condition 'night'; available: summer"):
        ds["night"]


def test_traverse_select_and_frames_keep_frame_ids(tmp_path):
    t = Traverse("a", [tmp_path / f"{i}.png" for i in range(10)], positions=np.arange(20.0).reshape(10, 2))
    part = t.frames(3, 7)
    assert list(part.frame_ids) == [3, 4, 5, 6] and len(part) == 4
    assert part.paths[0].name == "3.png"
    again = part.select([0, 2])
    assert list(again.frame_ids) == [3, 5]
    np.testing.assert_array_equal(again.positions, [[6, 7], [10, 11]])
    with pytest.raises(ValueError):
        Traverse("b", [tmp_path / "x.png"], frame_ids=[0, 1])


def test_dataset_frames_slices_every_condition(tmp_path):
    ds = RouteDataset.from_folder(_make(tmp_path, {"a": 5, "b": 5})).frames(1, None)
    assert all(list(t.frame_ids) == [1, 2, 3, 4] for t in ds.traverses.values())


@pytest.mark.parametrize(
    "text, expected",
    [("0:10", (0, 10)), (":5", (None, 5)), ("3:", (3, None)), ("", (None, None)), (None, (None, None))],
)
def test_parse_frame_range(text, expected):
    assert parse_frame_range(text) == expected


@pytest.mark.parametrize(
    "text, message",
    [
        ("10", "expected START:END"),
        ("a:b", "must be integers"),
        ("5:5", "greater than START"),
        ("9:2", "greater than START"),
    ],
)
def test_parse_frame_range_errors(text, message):
    with pytest.raises(DataError, match=message):
        parse_frame_range(text)


def test_aligned_split_ground_truth_and_range(tmp_path):
    ds = RouteDataset.from_folder(_make(tmp_path, {"ref": 8, "qry": 8}))
    split = aligned_split(ds, "ref", "qry", tolerance=1, start=2, end=6)
    assert len(split.reference) == len(split.query) == 4
    assert [list(p) for p in split.ground_truth.positives] == [[0, 1], [0, 1, 2], [1, 2, 3], [2, 3]]
    assert "qry -> ref" in split.description


def test_aligned_split_refuses_different_frame_counts_naming_both_folders(tmp_path):
    ds = RouteDataset.from_folder(_make(tmp_path, {"ref": 5, "qry": 4}))
    with pytest.raises(DataError, match=r"ref has 5 images and .*qry has 4"):
        aligned_split(ds, "ref", "qry", tolerance=0)


def test_aligned_split_empty_range_and_unknown_condition(tmp_path):
    ds = RouteDataset.from_folder(_make(tmp_path, {"ref": 3, "qry": 3}))
    with pytest.raises(DataError, match="selects no images"):
        aligned_split(ds, "ref", "qry", tolerance=0, start=10, end=20)
    with pytest.raises(DataError, match="no condition 'night'"):
        aligned_split(ds, "ref", "night", tolerance=0)


def test_evaluation_split_checks_ground_truth_size(tmp_path):
    ds = RouteDataset.from_folder(_make(tmp_path, {"ref": 3, "qry": 3}))
    with pytest.raises(DataError, match="ground truth is for 2 queries x 3 references"):
        EvaluationSplit(ds["ref"], ds["qry"], GroundTruth.aligned(2, 3, 0))


def test_real_nordland_test_split():
    root = require_shared("nordland_trimmed")
    ds = RouteDataset.from_folder(root)
    assert ds.conditions == ["summer", "winter"]
    assert len(ds["summer"]) == len(ds["winter"]) == 2576
    assert ds["summer"].paths[0].name == "images-00010.png" and ds["winter"].paths[-1].name == "images-25760.png"
    split = aligned_split(ds, "summer", "winter", tolerance=0, start=1576, end=2576)
    assert split.ground_truth.num_queries == 1000
    assert all(list(p) == [i] for i, p in enumerate(split.ground_truth.positives))
    assert split.query.frame_ids[0] == 1576


def test_real_gardens_point_conditions():
    root = require_shared("gardens_point")
    ds = RouteDataset.from_folder(root)
    assert set(ds.conditions) == {"day_left", "day_right", "night_right"}
    split = aligned_split(ds, "day_right", "night_right", tolerance=2, start=100, end=200)
    counts = [len(p) for p in split.ground_truth.positives]
    assert counts[0] == 3 and counts[50] == 5 and counts[-1] == 3
