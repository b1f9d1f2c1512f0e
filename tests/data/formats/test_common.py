"""Shared adapter pieces: file order, frame numbers, correspondence files, size checks, splits."""

import pytest

from fdnet.data.dataset import Traverse
from fdnet.data.formats._common import (
    check_image_sizes,
    fixed,
    frame_number,
    ground_truth_from_correspondences,
    list_images,
    natural_key,
    read_correspondences,
    resolve_split,
)
from fdnet.errors import ConfigError, DataError

from .conftest import write_frames, write_image


def test_natural_order_and_frame_numbers(tmp_path):
    write_frames(tmp_path, ["10.png", "2.png", "1.png"])
    assert [p.name for p in list_images(tmp_path)] == ["1.png", "2.png", "10.png"]
    assert frame_number("images-00010.png") == 10
    assert frame_number("Image00042.jpg") == 42
    assert frame_number("section2/17.png") == 17
    assert frame_number("night.png") is None
    assert sorted(["a10", "a9"], key=natural_key) == ["a9", "a10"]


def test_read_correspondences_csv_with_header(tmp_path):
    path = tmp_path / "fm.csv"
    path.write_text("night,day\n1,3\n2,5\n")
    corr = read_correspondences(path)
    assert corr.query == [1, 2] and corr.reference == [3, 5] and not corr.by_name


def test_read_correspondences_whitespace_and_names(tmp_path):
    path = tmp_path / "gt.txt"
    path.write_text("# comment\nq_001.png  m_004.png\nq_002.png  m_006.png\n")
    corr = read_correspondences(path)
    assert corr.by_name and corr.query == ["q_001", "q_002"] and corr.reference == ["m_004", "m_006"]


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty correspondence file"),
        ("1\n2\n", "line 1: expected at least 2 columns"),
        ("1,2\n3,4.5\n", "line 2: frame numbers must be integers"),
    ],
)
def test_read_correspondences_errors(tmp_path, text, message):
    path = tmp_path / "fm.csv"
    path.write_text(text)
    with pytest.raises(DataError, match=message):
        read_correspondences(path)


def test_missing_correspondence_file_is_named(tmp_path):
    with pytest.raises(DataError, match="fm.csv: correspondence"):
        read_correspondences(tmp_path / "fm.csv")


def test_ground_truth_from_correspondences_uses_frame_numbers(tmp_path):
    path = tmp_path / "fm.csv"
    path.write_text("1,11\n2,13\n")
    corr = read_correspondences(path)
    query = Traverse("q", [tmp_path / f"q{i}.png" for i in (1, 2, 3)], frame_ids=[1, 2, 3])
    reference = Traverse("r", [tmp_path / f"r{i}.png" for i in range(10, 16)], frame_ids=range(10, 16))
    gt = ground_truth_from_correspondences(corr, query, reference, tolerance=1)
    # query 1 <-> ref frame 11 +-1 = frames 10,11,12 = positions 0,1,2; query 3 has no row
    assert [p.tolist() for p in gt.positives] == [[0, 1, 2], [2, 3, 4], []]


def test_mixed_image_sizes_in_one_condition(tmp_path):
    write_image(tmp_path / "a.png", (8, 6))
    write_image(tmp_path / "b.png", (8, 6))
    write_image(tmp_path / "c.png", (10, 6))
    traverse = Traverse("day", list_images(tmp_path))
    with pytest.raises(DataError, match=r"mixed image sizes.*a.png is 8x6 but c.png is 10x6"):
        check_image_sizes(traverse)
    assert check_image_sizes(traverse.frames(0, 2)) == (8, 6)


def test_resolve_split():
    rules = {"test": fixed(0, 10), "train": fixed(10, None)}
    assert resolve_split("test", rules, 50, "x") == (0, 10)
    assert resolve_split("5:8", rules, 50, "x") == (5, 8)
    assert resolve_split("all", rules, 50, "x") == (None, None)
    with pytest.raises(ConfigError, match="no split named 'val'"):
        resolve_split("val", rules, 50, "x")
    with pytest.raises(DataError, match="has only 8 frames"):
        resolve_split("train", rules, 8, "x")
