"""Position files: image column + lat,lon degrees or easting,northing metres."""

import pytest

from fdnet.data.formats.positions import positions_ground_truth, read_positions
from fdnet.errors import DataError


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_degrees_and_metres(tmp_path):
    ref = read_positions(write(tmp_path, "r.csv", "Image,Latitude,Longitude\na,-27.5,153.0\nb,-27.5003,153.0\n"))
    assert ref.kind == "degrees" and ref.images == ["a", "b"]
    qry = read_positions(write(tmp_path, "q.csv", "image,lat,lon\nq,-27.5001,153.0\n"))
    gt = positions_ground_truth(ref, qry, 25.0)  # 0.0001 deg of latitude = 11.1 m; b is 22.2 m away
    assert gt.positives[0].tolist() == [0, 1]
    assert positions_ground_truth(ref, qry, 15.0).positives[0].tolist() == [0]
    metric = read_positions(write(tmp_path, "m.csv", "filename;easting;northing\nx;500000;6000000\n"))
    assert metric.kind == "metres" and metric.values.tolist() == [[500000.0, 6000000.0]]


def test_headerless_with_column_meanings(tmp_path):
    table = read_positions(write(tmp_path, "fGPS.txt", "0 -27.5 153.0\n1 -27.6 153.1\n"), columns="-,lat,lon")
    assert table.kind == "degrees" and table.images is None and table.values[1].tolist() == [-27.6, 153.1]


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty position file"),
        ("image,lat\na,1\n", "missing position columns; need lat,lon .* found: image, lat"),
        ("image,lat,lon\n", "has a header but no position rows"),
        ("image,lat,lon\na,1,2\nb,1,east\n", "line 3: lon is not a number: 'east'"),
        ("image,lat,lon\na,1,nan\n", "line 2: lon is not a finite number"),
        ("image,lat,lon\na,95,2\n", "line 2: latitude 95, longitude 2 out of range"),
        ("1,2,3\n4,5,6\n", "line 1: no header"),
        ("image,lat,lon\na,1\n", "line 2: expected 3 columns"),
    ],
)
def test_bad_position_files(tmp_path, text, message):
    with pytest.raises(DataError, match=message):
        read_positions(write(tmp_path, "p.csv", text))


def test_mixed_units_are_refused(tmp_path):
    ref = read_positions(write(tmp_path, "r.csv", "image,lat,lon\na,1,2\n"))
    qry = read_positions(write(tmp_path, "q.csv", "image,easting,northing\na,1,2\n"))
    with pytest.raises(DataError, match="same units"):
        positions_ground_truth(ref, qry, 25)


def test_a_file_saved_with_a_byte_order_mark_is_read(tmp_path):
    """Excel's "CSV UTF-8" starts the file with U+FEFF, which must not become part of "image"."""
    path = tmp_path / "excel.csv"
    path.write_bytes("\ufeffimage,lat,lon\na.png,-27.5,153.0\n".encode("utf-8"))
    table = read_positions(path)
    assert table.images == ["a.png"] and table.values.tolist() == [[-27.5, 153.0]]
