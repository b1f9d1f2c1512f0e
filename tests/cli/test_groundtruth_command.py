"""`fdnet groundtruth`: position files, frame alignment, dataset folders; bad input."""

import numpy as np
import pytest
from PIL import Image

from fdnet.cli import main
from fdnet.data.groundtruth import GroundTruth


def write(path, text):
    path.write_text(text)
    return str(path)


def test_positions_in_degrees(tmp_path, capsys):
    ref = write(tmp_path / "ref.csv", "image,lat,lon\nr0.jpg,-27.5,153.0\nr1.jpg,-27.5002,153.0\nr2.jpg,-27.6,153.0\n")
    qry = write(tmp_path / "qry.csv", "image,lat,lon\nq0.jpg,-27.50005,153.0\nq1.jpg,-27.7,153.0\n")
    out = tmp_path / "gt.csv"
    assert main(["groundtruth", "--positions", ref, qry, "--tolerance-m", "25", "--out", str(out)]) == 0
    gt = GroundTruth.from_csv(out, num_references=3, num_queries=2)
    assert [p.tolist() for p in gt.positives] == [[0, 1], []]
    captured = capsys.readouterr()
    assert "queries with at least one true match: 1/2 (50.0 %)" in captured.out
    assert "mean true matches per query: 1.00" in captured.out
    assert "warning: 1 of 2 queries (50.0 %) have no true match" in captured.err


def test_positions_in_metres_no_warning(tmp_path, capsys):
    ref = write(tmp_path / "ref.csv", "name,easting,northing\na,500000,6000000\nb,500010,6000000\n")
    qry = write(tmp_path / "qry.csv", "name,easting,northing\nc,500004,6000000\n")
    out = tmp_path / "gt.csv"
    assert main(["groundtruth", "--positions", ref, qry, "--tolerance-m", "5", "--out", str(out)]) == 0
    assert out.read_text() == "query_index,reference_indices\n0,0\n"
    assert "warning" not in capsys.readouterr().err


def test_aligned_counts_and_folders(tmp_path):
    out = tmp_path / "gt.csv"
    assert main(["groundtruth", "--aligned", "--num-queries", "4", "--num-references", "4",
                 "--tolerance-frames", "1", "--out", str(out)]) == 0
    assert out.read_text().splitlines()[1:] == ["0,0 1", "1,0 1 2", "2,1 2 3", "3,2 3"]
    for name in ("day", "night"):
        (tmp_path / name).mkdir()
        for i in range(3):
            Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / name / f"{i}.png")
    assert main(["groundtruth", "--aligned", "--reference", str(tmp_path / "day"), "--query",
                 str(tmp_path / "night"), "--out", str(out)]) == 0
    assert out.read_text().splitlines()[1:] == ["0,0", "1,1", "2,2"]


def test_dataset_folder_with_setting(tmp_path, capsys):
    for name in ("day", "night"):
        (tmp_path / "route" / name).mkdir(parents=True)
        for i in range(5):
            Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / "route" / name / f"{i}.png")
    out = tmp_path / "gt.csv"
    assert main(["groundtruth", "--dataset", str(tmp_path / "route"), "--set", "tolerance=2",
                 "--split", "1:4", "--out", str(out)]) == 0
    assert out.read_text().splitlines()[1:] == ["0,0 1 2", "1,0 1 2", "2,0 1 2"]


@pytest.mark.parametrize("text, message", [
    ("", "empty position file"),
    ("image,lat\na,1\n", "missing position columns"),
    ("image,lat,lon\na,1,2\nb,x,2\n", "line 3: lat is not a number"),
])
def test_bad_position_files(tmp_path, capsys, text, message):
    bad = write(tmp_path / "bad.csv", text)
    good = write(tmp_path / "good.csv", "image,lat,lon\na,1,2\n")
    assert main(["groundtruth", "--positions", bad, good, "--out", str(tmp_path / "gt.csv")]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and message in err and "Traceback" not in err
    assert not (tmp_path / "gt.csv").exists()


def test_inconsistent_flags(tmp_path, capsys):
    assert main(["groundtruth", "--aligned", "--num-queries", "3", "--out", str(tmp_path / "g.csv")]) == 2
    assert "--aligned needs --num-queries and --num-references" in capsys.readouterr().err
    assert main(["groundtruth", "--aligned", "--num-queries", "3", "--num-references", "3",
                 "--tolerance-m", "4", "--out", str(tmp_path / "g.csv")]) == 2
    assert "--tolerance-m is for --positions" in capsys.readouterr().err
