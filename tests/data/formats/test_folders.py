"""The plain one-folder-per-condition layout."""

import pytest

from fdnet.data.formats import detect_format, open_split, open_training
from fdnet.errors import ConfigError, DataError

from .conftest import write_frames
from conftest import require_shared


def make_route(root, conditions=("day", "night"), n=6):
    for c in conditions:
        write_frames(root / c, [f"frame{i:03d}.png" for i in range(n)])
    return root


def test_two_conditions_frame_aligned(tmp_path):
    root = make_route(tmp_path / "route")
    assert detect_format(root) == "folders"
    split = open_split(root, tolerance=1)
    assert (split.reference.name, split.query.name) == ("day", "night")
    assert [p.tolist() for p in split.ground_truth.positives] == [
        [0, 1],
        [0, 1, 2],
        [1, 2, 3],
        [2, 3, 4],
        [3, 4, 5],
        [4, 5],
    ]
    part = open_split(root, reference="night", query="day", split="2:5")
    assert len(part.query) == 3 and part.query.frame_ids.tolist() == [2, 3, 4]
    assert [p.tolist() for p in part.ground_truth.positives] == [[0], [1], [2]]


def test_explicit_ground_truth_csv(tmp_path):
    root = make_route(tmp_path / "route")
    (root / "gt.csv").write_text("query_index,reference_indices\n0,5\n1,4 3\n")
    split = open_split(root, ground_truth="gt.csv")
    assert split.ground_truth.positives[1].tolist() == [3, 4]
    assert split.ground_truth.has_match.sum() == 2


def test_three_conditions_need_a_pair(tmp_path):
    root = make_route(tmp_path / "route", ("a", "b", "c"))
    with pytest.raises(ConfigError, match="name the pair with --reference and --query"):
        open_split(root)
    assert len(open_split(root, reference="a", query="c").query) == 6


def test_unequal_lengths_are_an_error(tmp_path):
    root = make_route(tmp_path / "route")
    (root / "night" / "frame005.png").unlink()
    with pytest.raises(DataError, match="has 6 images and .*night has 5"):
        open_split(root)


def test_mixed_sizes_are_reported(tmp_path):
    root = make_route(tmp_path / "route")
    write_frames(root / "night", ["frame005.png"], size=(12, 6))
    with pytest.raises(DataError, match="mixed image sizes in condition 'night'"):
        open_split(root)


def test_unknown_setting_names_the_valid_ones(tmp_path):
    root = make_route(tmp_path / "route")
    with pytest.raises(ConfigError, match="unknown setting.*tolerence.*valid: tolerance, ground_truth"):
        open_split(root, tolerence=3)


def test_training_dataset(tmp_path):
    root = make_route(tmp_path / "route", n=8)
    route = open_training(root, split="0:5")
    assert route.conditions == ["day", "night"] and len(route["day"]) == 5


@pytest.mark.shared_data
def test_real_gardens_point():
    root = require_shared("gardens_point")
    split = open_split(root)
    assert (split.reference.name, split.query.name) == ("day_right", "night_right")
    assert len(split.query) == 200 and split.ground_truth.has_match.all()
    assert split.ground_truth.positives[100].tolist() == [98, 99, 100, 101, 102]  # VPR-Bench's +-2
