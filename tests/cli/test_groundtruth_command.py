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
    assert out.read_text() == "query_index,reference_indices,query_name,reference_names\n0,0,c,a\n"
    assert "warning" not in capsys.readouterr().err


def test_aligned_counts_and_folders(tmp_path):
    out = tmp_path / "gt.csv"
    assert (
        main(
            [
                "groundtruth",
                "--aligned",
                "--num-queries",
                "4",
                "--num-references",
                "4",
                "--tolerance",
                "1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert out.read_text().splitlines()[1:] == ["0,0 1", "1,0 1 2", "2,1 2 3", "3,2 3"]
    for name in ("day", "night"):
        (tmp_path / name).mkdir()
        for i in range(3):
            Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / name / f"{i}.png")
    assert (
        main(
            [
                "groundtruth",
                "--aligned",
                "--reference",
                str(tmp_path / "day"),
                "--query",
                str(tmp_path / "night"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert out.read_text().splitlines()[1:] == ["0,0,0.png,0.png", "1,1,1.png,1.png", "2,2,2.png,2.png"]


def write_two_condition_folders(root, n=5):
    """root/day and root/night: n blank 4x4 images each, named 0.png ... (frame-aligned)."""
    for name in ("day", "night"):
        (root / name).mkdir(parents=True)
        for i in range(n):
            Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(root / name / f"{i}.png")


def test_dataset_folder_with_setting(tmp_path, capsys):
    write_two_condition_folders(tmp_path / "route")
    out = tmp_path / "gt.csv"
    assert (
        main(
            [
                "groundtruth",
                "--data",
                str(tmp_path / "route"),
                "--format-set",
                "tolerance=2",
                "--split",
                "1:4",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert out.read_text().splitlines()[1:] == [
        "0,0 1 2,1.png,1.png/2.png/3.png",
        "1,0 1 2,2.png,1.png/2.png/3.png",
        "2,0 1 2,3.png,1.png/2.png/3.png",
    ]


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty position file"),
        ("image,lat\na,1\n", "missing position columns"),
        ("image,lat,lon\na,1,2\nb,x,2\n", "line 3: lat is not a number"),
    ],
)
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
    assert (
        main(
            [
                "groundtruth",
                "--aligned",
                "--num-queries",
                "3",
                "--num-references",
                "3",
                "--tolerance-m",
                "4",
                "--out",
                str(tmp_path / "g.csv"),
            ]
        )
        == 2
    )
    assert "--tolerance-m is for --positions" in capsys.readouterr().err


def test_positions_rows_in_any_order_give_indices_in_natural_file_order(tmp_path):
    """Rows are put in natural order of their image names (frame_2 before frame_10), the order
    every command lists the folder in, and the names are written beside the indices."""
    ref = write(
        tmp_path / "ref.csv",
        "image,easting,northing\n" + "".join(f"frame_{k}.png,{10 * k},0\n" for k in (10, 1, 2, 11, 3)),
    )  # any row order
    qry = write(tmp_path / "qry.csv", "image,easting,northing\nframe_2.png,100,0\nframe_1.png,20,0\n")
    out = tmp_path / "gt.csv"
    assert main(["groundtruth", "--positions", ref, qry, "--tolerance-m", "1", "--out", str(out)]) == 0
    assert out.read_text().splitlines() == [
        "query_index,reference_indices,query_name,reference_names",
        "0,1,frame_1.png,frame_2.png",  # references in natural order: 1, 2, 3, 10, 11
        "1,3,frame_2.png,frame_10.png",
    ]


def test_positions_matched_to_image_folders(tmp_path):
    for name in ("ref", "qry"):
        for k in (1, 2, 10):
            (tmp_path / name).mkdir(exist_ok=True)
            Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / name / f"f{k}.png")
    # no image column: one row per image, in the folder's (natural) order
    ref = write(tmp_path / "ref.csv", "easting,northing\n0,0\n10,0\n20,0\n")
    qry = write(tmp_path / "qry.csv", "easting,northing\n20,0\n0,0\n10,0\n")
    out = tmp_path / "gt.csv"
    assert (
        main(
            [
                "groundtruth",
                "--positions",
                ref,
                qry,
                "--reference",
                str(tmp_path / "ref"),
                "--query",
                str(tmp_path / "qry"),
                "--tolerance-m",
                "1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert out.read_text().splitlines()[1:] == ["0,2,f1.png,f10.png", "1,0,f2.png,f1.png", "2,1,f10.png,f2.png"]


def test_unwritable_out_fails_before_any_work(tmp_path, capsys):
    ref = write(tmp_path / "ref.csv", "image,easting,northing\na.png,0,0\n")
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    out = blocker / "gt.csv"
    # the query position file is missing too: the output is refused first
    assert main(["groundtruth", "--positions", ref, str(tmp_path / "absent.csv"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(out) in err and "cannot create the ground-truth CSV" in err and "Traceback" not in err


def test_position_files_saved_by_a_spreadsheet_with_a_byte_order_mark(tmp_path):
    import csv

    from fdnet.cli import main

    for name in ("ref.csv", "qry.csv"):
        (tmp_path / name).write_bytes("\ufeffimage,lat,lon\na.png,-27.5,153.0\nb.png,-27.6,153.0\n".encode())
    out = tmp_path / "gt.csv"
    assert (
        main(["groundtruth", "--positions", str(tmp_path / "ref.csv"), str(tmp_path / "qry.csv"), "--out", str(out)])
        == 0
    )
    with open(out, newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["query_name"], r["reference_names"]) for r in rows] == [("a.png", "a.png"), ("b.png", "b.png")]


def test_tolerances_are_used_or_refused_never_dropped(tmp_path, capsys):
    write_two_condition_folders(tmp_path / "route")
    out = tmp_path / "gt.csv"
    # --tolerance with --data is the format's tolerance (it was silently 0)
    assert (
        main(
            [
                "groundtruth",
                "--data",
                str(tmp_path / "route"),
                "--dataset-format",
                "folders",
                "--tolerance",
                "2",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert out.read_text().splitlines()[1].startswith("0,0 1 2,")
    assert (
        main(
            [
                "groundtruth",
                "--data",
                str(tmp_path / "route"),
                "--tolerance",
                "2",
                "--format-set",
                "tolerance=1",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    assert "disagree" in capsys.readouterr().err
    ref = write(tmp_path / "ref.csv", "name,easting,northing\na,500000,6000000\n")
    for bad in ("nan", "inf", "-1"):
        assert main(["groundtruth", "--positions", ref, ref, "--tolerance-m", bad, "--out", str(out)]) == 2
        assert "a position tolerance must be a finite number of metres >= 0" in capsys.readouterr().err
