"""Geo-localization benchmark layout: UTM easting/northing in the file names."""

import pytest

from fdnet.data.formats import detect_format, open_split, open_training
from fdnet.errors import DataError

from .conftest import write_image


def name(east, north):
    return f"@{east:.2f}@{north:.2f}@55@J@-27.49@153.01@@@@@@@@.jpg"


def make_split(folder, db_east, q_east):
    for e in db_east:
        write_image(folder / "database" / name(e, 6960000.0))
    for e in q_east:
        write_image(folder / "queries" / name(e, 6960010.0))


def test_positions_from_file_names(tmp_path):
    root = tmp_path / "st_lucia"
    make_split(root / "images" / "test", [500000.0, 500020.0, 500100.0], [500005.0, 500300.0])
    make_split(root / "images" / "train", [500000.0], [500001.0])
    assert detect_format(root) == "vg_benchmark"
    split = open_split(root)  # test, 25 m
    # query 0 is 11.2 m from db 0 and 18.0 m from db 1; query 1 is far from all
    assert [p.tolist() for p in split.ground_truth.positives] == [[0, 1], []]
    assert [p.tolist() for p in open_split(root, tolerance_m=15).ground_truth.positives] == [[0], []]
    assert len(open_training(root)["database"]) == 1
    with pytest.raises(DataError, match="images/val: folder not found; splits here: test, train"):
        open_split(root, split="val")


def test_name_without_position(tmp_path):
    root = tmp_path / "ds"
    make_split(root / "images" / "test", [500000.0], [500000.0])
    write_image(root / "images" / "test" / "queries" / "photo.jpg")
    with pytest.raises(DataError, match="photo.jpg: file name does not carry its position"):
        open_split(root, dataset_format="vg_benchmark")
