"""Alderley: FRAMESA (night), FRAMESB (day) and the frame-correspondence file."""

import pytest

from fdnet.data.formats import detect_format, open_split, open_training
from fdnet.errors import ConfigError, DataError

from .conftest import write_frames


def make_alderley(root, n_a=8, n_b=10, rows=None):
    write_frames(root / "FRAMESA", [f"Image{i:05d}.jpg" for i in range(1, n_a + 1)])
    write_frames(root / "FRAMESB", [f"Image{i:05d}.jpg" for i in range(1, n_b + 1)])
    # the night drive is slower at first: night frame k <-> day frame k + 2 (1-based numbers)
    rows = rows if rows is not None else [(k, k + 2) for k in range(1, n_a + 1)]
    (root / "framematches.csv").write_text("".join(f"{a},{b}\n" for a, b in rows))
    return root


def test_ground_truth_from_correspondences(tmp_path):
    root = make_alderley(tmp_path / "alderley")
    assert detect_format(root) == "alderley"
    split = open_split(root, split="all")
    assert (split.reference.name, split.query.name) == ("day", "night")
    # night frame 1 <-> day frame 3 (position 2), +-2 frames -> positions 0..4
    assert split.ground_truth.positives[0].tolist() == [0, 1, 2, 3, 4]
    assert split.ground_truth.positives[7].tolist() == [7, 8, 9]


def test_test_split_and_reference_stretch(tmp_path, monkeypatch):
    import fdnet.data.formats.alderley as alderley
    from fdnet.data.formats._common import fixed

    monkeypatch.setattr(alderley.FORMAT, "split_rules", {"test": fixed(0, 3), "train": fixed(3, None)})
    root = make_alderley(tmp_path / "alderley")
    test = open_split(root)
    assert test.query.frame_ids.tolist() == [1, 2, 3]
    # queries 1..3 <-> day 3..5, widened by the tolerance: day frames 1..7
    assert test.reference.frame_ids.tolist() == [1, 2, 3, 4, 5, 6, 7]
    train = open_training(root)
    assert train["night"].frame_ids.tolist() == [4, 5, 6, 7, 8]
    assert train["day"].frame_ids.tolist() == [8, 9, 10]


def test_swapped_roles(tmp_path):
    root = make_alderley(tmp_path / "alderley")
    split = open_split(root, reference="FRAMESA", query="day", split="all", tolerance=0)
    assert split.query.name == "day" and split.ground_truth.positives[2].tolist() == [0]  # day 3 <-> night 1
    assert not split.ground_truth.has_match[0]  # day frame 1 has no night counterpart


def test_missing_correspondence_file(tmp_path):
    root = make_alderley(tmp_path / "alderley")
    (root / "framematches.csv").unlink()
    with pytest.raises(DataError, match="missing the frame-correspondence file"):
        open_split(root)


def test_correspondences_of_another_dataset(tmp_path):
    root = make_alderley(tmp_path / "alderley", rows=[(500, 600), (501, 601)])
    with pytest.raises(DataError, match="none of its query frames"):
        open_split(root, split="all")


def test_missing_day_folder(tmp_path):
    root = make_alderley(tmp_path / "alderley")
    for p in (root / "FRAMESB").iterdir():
        p.unlink()
    (root / "FRAMESB").rmdir()
    with pytest.raises(DataError, match="missing the day image folder"):
        open_split(root, dataset_format="alderley")


def test_numbering_by_position(tmp_path):
    """A file that counts frames by position while the image names carry other numbers."""
    root = tmp_path / "alderley"
    write_frames(root / "FRAMESA", [f"Image{i:05d}.jpg" for i in range(101, 105)])
    write_frames(root / "FRAMESB", [f"Image{i:05d}.jpg" for i in range(201, 206)])
    (root / "framematches.csv").write_text("0,1\n1,2\n2,3\n3,4\n")
    with pytest.raises(DataError, match="none of its query frames"):
        open_split(root, split="all")  # read as image numbers, nothing matches
    split = open_split(root, split="all", tolerance=0, numbering="positions")
    assert [p.tolist() for p in split.ground_truth.positives] == [[1], [2], [3], [4]]
    with pytest.raises(ConfigError, match="numbering 'zero'"):
        open_split(root, numbering="zero")
