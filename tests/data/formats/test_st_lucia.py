"""St Lucia: run folders (DDMMYY_HHMM) of frames with their GPS fixes."""

import pytest

from fdnet.data.formats import detect_format, open_split, open_training
from fdnet.errors import DataError

from .conftest import write_frames

LAT0, LON0 = -27.4975, 153.0137
DEG_PER_M = 1 / 111_195.0  # degrees of latitude per metre


def make_run(root, name, n, offset_m=0.0, step_m=10.0, header=True):
    run = root / name
    write_frames(run / "frames", [f"{i:05d}.png" for i in range(n)])
    lines = ["frame,latitude,longitude"] if header else []
    for i in range(n):
        lines.append(f"{i},{LAT0 + (offset_m + i * step_m) * DEG_PER_M:.8f},{LON0}")
    (run / "fGPS.txt").write_text("\n".join(lines) + "\n")
    return run


def test_ground_truth_within_30_m(tmp_path):
    root = tmp_path / "st_lucia"
    make_run(root, "190809_0845", 8)
    make_run(root, "180809_1545", 8, offset_m=25.0)  # the afternoon run is 25 m further along
    make_run(root, "100909_0845", 8)
    assert detect_format(root) == "st_lucia"
    split = open_split(root, split="all")
    assert (split.reference.name, split.query.name) == ("190809_0845", "180809_1545")
    # query i is at 25 + 10 i m; references at 10 j m; within 30 m: j in i..i+5 (|10j - 10i - 25| <= 30)
    assert split.ground_truth.positives[0].tolist() == [0, 1, 2, 3, 4, 5]
    assert split.ground_truth.positives[7].tolist() == [7]
    assert split.reference.positions.shape == (8, 2)
    part = open_split(root, split="2:4", tolerance_m=5.0)
    assert len(part.query) == 2 and [p.tolist() for p in part.ground_truth.positives] == [[], []]


def test_headerless_gps_with_column_meanings(tmp_path):
    root = tmp_path / "st_lucia"
    make_run(root, "190809_0845", 4, header=False)
    make_run(root, "180809_1545", 4, header=False)
    with pytest.raises(DataError, match="no header"):
        open_split(root, split="all")
    split = open_split(root, split="all", gps_columns="-,lat,lon", tolerance_m=35)
    assert split.ground_truth.positives[0].tolist() == [0, 1, 2, 3]


def test_gps_rows_must_cover_every_frame(tmp_path):
    root = tmp_path / "st_lucia"
    make_run(root, "190809_0845", 4)
    run = make_run(root, "180809_1545", 4)
    write_frames(run / "frames", ["00004.png"])
    with pytest.raises(DataError, match="has 4 position rows but .*frames has 5 images"):
        open_split(root, split="all")


def test_missing_gps_file(tmp_path):
    root = tmp_path / "st_lucia"
    make_run(root, "190809_0845", 4)
    (make_run(root, "180809_1545", 4) / "fGPS.txt").unlink()
    with pytest.raises(DataError, match="180809_1545: missing the GPS file"):
        open_split(root, split="all")


def test_training_split_too_long_for_copy(tmp_path):
    root = tmp_path / "st_lucia"
    make_run(root, "190809_0845", 4)
    make_run(root, "180809_1545", 4)
    route = open_training(root)  # train = frames 0:3500, the copy has 4
    assert len(route["190809_0845"]) == 4
    with pytest.raises(DataError, match="split 'test' is frames 3500:4000 but this copy has only 4 frames"):
        open_split(root)
