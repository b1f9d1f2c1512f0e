"""Ground truth: frame-aligned, positions, explicit CSV lists; errors name file and line."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.data.groundtruth import GroundTruth, latlon_to_metres
from fdnet.errors import DataError

from conftest import require_shared


def _lists(gt):
    return [list(map(int, p)) for p in gt.positives]


def test_from_frames_tolerance():
    gt = GroundTruth.from_frames([0, 5, 9], np.arange(10), tolerance=2)
    assert _lists(gt) == [[0, 1, 2], [3, 4, 5, 6, 7], [7, 8, 9]]
    assert gt.num_references == 10 and "tolerance 2 frames" in gt.description
    assert _lists(GroundTruth.from_frames([4], np.arange(10), 0)) == [[4]]
    with pytest.raises(DataError, match="tolerance must be >= 0"):
        GroundTruth.from_frames([0], [0], -1)


def test_from_frames_compares_frame_ids_not_positions():
    """After filtering, reference frame ids have gaps; positives are list positions."""
    refs = np.array([0, 1, 2, 6, 7, 10])  # frames 3-5, 8-9 were dropped (tunnel, stop)
    gt = GroundTruth.from_frames([2, 4, 8, 10], refs, tolerance=1)
    assert _lists(gt) == [[1, 2], [], [4], [5]]
    assert list(gt.has_match) == [True, False, True, True]
    unsorted = GroundTruth.from_frames([7], np.array([7, 3, 6]), tolerance=1)
    assert _lists(unsorted) == [[0, 2]]


def test_aligned():
    gt = GroundTruth.aligned(3, 5, 1)
    assert _lists(gt) == [[0, 1], [0, 1, 2], [1, 2, 3]] and gt.num_references == 5


def test_from_positions_metres():
    refs = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [100.0, 100.0]])
    queries = np.array([[1.0, 1.0], [15.0, 0.0], [500.0, 500.0]])
    gt = GroundTruth.from_positions(queries, refs, tolerance_m=6.0)
    assert _lists(gt) == [[0], [1, 2], []]
    with pytest.raises(DataError, match=r"\(N, 2\)"):
        GroundTruth.from_positions(np.zeros(3), refs, 5.0)


def test_latlon_to_metres_scale():
    xy = latlon_to_metres(np.array([52.0, 52.001]), np.array([13.0, 13.0]), origin=(52.0, 13.0))
    assert xy[0] == pytest.approx([0.0, 0.0])
    assert xy[1][1] == pytest.approx(111.2, abs=0.2)  # 0.001 degree of latitude ~ 111 m
    east = latlon_to_metres(np.array([52.0]), np.array([13.001]), origin=(52.0, 13.0))
    assert east[0][0] == pytest.approx(111.2 * np.cos(np.radians(52.0)), abs=0.2)


def test_csv_round_trip(tmp_path):
    gt = GroundTruth([np.array([2, 0]), np.array([], dtype=np.int64), np.array([3])], num_references=4)
    gt.to_csv(tmp_path / "gt.csv")
    text = (tmp_path / "gt.csv").read_text()
    assert text.splitlines() == ["query_index,reference_indices", "0,0 2", "1,", "2,3"]
    back = GroundTruth.from_csv(tmp_path / "gt.csv", num_references=4, num_queries=3)
    assert _lists(back) == [[0, 2], [], [3]] and back.num_references == 4


def test_csv_without_header_and_missing_queries(tmp_path):
    path = tmp_path / "gt.csv"
    path.write_text("0,1\n\n3,2 4\n")
    gt = GroundTruth.from_csv(path)
    assert gt.num_queries == 4 and gt.num_references == 5
    assert _lists(gt) == [[1], [], [], [2, 4]]


def test_csv_with_byte_order_mark(tmp_path):
    """Spreadsheet programs write UTF-8 with a BOM; the header must still be recognised."""
    path = tmp_path / "gt.csv"
    path.write_bytes("query_index,reference_indices\n0,0 1\n".encode("utf-8-sig"))
    assert _lists(GroundTruth.from_csv(path)) == [[0, 1]]


@pytest.mark.parametrize(
    "body, message",
    [
        ("0,1\n1,7\n", r"line 3: reference index 7 out of range \(0..4\)"),
        ("0,1\n5,1\n", r"line 3: query index 5 out of range \(0..2\)"),
        ("0,1\n-1,1\n", "line 3: query index -1 out of range"),
        ("0,1\n1,2 x\n", "line 3: non-integer value"),
        ("0,1\nabc,2\n", "line 3: non-integer value"),
        ("0,1.5\n", "line 2: non-integer value"),
        ("0,1\n0,2\n", "line 3: query 0 listed twice"),
        ("0,1,2\n", "line 2: expected 'query_index,reference_indices'"),
    ],
)
def test_csv_errors_name_file_and_line(tmp_path, body, message):
    path = tmp_path / "bad_gt.csv"
    path.write_text("query_index,reference_indices\n" + body)
    with pytest.raises(DataError, match=message) as info:
        GroundTruth.from_csv(path, num_references=5, num_queries=3)
    assert "bad_gt.csv" in str(info.value)


def test_csv_empty_missing_and_binary(tmp_path):
    with pytest.raises(DataError, match="not found"):
        GroundTruth.from_csv(tmp_path / "absent.csv")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(DataError, match="empty.csv: empty"):
        GroundTruth.from_csv(tmp_path / "empty.csv")
    (tmp_path / "header.csv").write_text("query_index,reference_indices\n")
    with pytest.raises(DataError, match="no ground-truth rows"):
        GroundTruth.from_csv(tmp_path / "header.csv")
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00\x81\x00")
    with pytest.raises(DataError, match="bin.csv"):
        GroundTruth.from_csv(tmp_path / "bin.csv")


def test_csv_with_names_round_trip_and_two_column_files_still_read(tmp_path):
    gt = GroundTruth([np.array([2, 0]), np.array([], dtype=np.int64)], num_references=3)
    path = tmp_path / "gt.csv"
    gt.to_csv(path, query_names=["q 1.png", "q,2.png"], reference_names=["r1.png", "r2.png", "r10.png"])
    assert path.read_text().splitlines() == [
        "query_index,reference_indices,query_name,reference_names",
        "0,0 2,q 1.png,r1.png/r10.png",  # names in the order of the indices
        '1,,"q,2.png",',
    ]  # a comma in a name is quoted, as CSV does
    back = GroundTruth.from_csv(path, num_references=3, num_queries=2)
    assert _lists(back) == [[0, 2], []]
    back.check_names(["/x/q 1.png", "/x/q,2.png"], ["/y/r1.png", "/y/r2.png", "/y/r10.png"])
    # the VPR-Bench form (no names) has nothing to check
    (tmp_path / "plain.csv").write_text("0,1\n1,0\n")
    plain = GroundTruth.from_csv(tmp_path / "plain.csv", num_references=2, num_queries=2)
    assert plain.listed_names is None
    plain.check_names(["a.png", "b.png"], ["c.png", "d.png"])


def test_names_that_do_not_match_the_images_name_row_file_and_both_names(tmp_path):
    gt = GroundTruth([np.array([0]), np.array([1]), np.array([2])], num_references=3)
    path = tmp_path / "gt.csv"
    names = ["frame_1.png", "frame_2.png", "frame_10.png"]
    gt.to_csv(path, query_names=names, reference_names=names)
    back = GroundTruth.from_csv(path, num_references=3, num_queries=3)
    text_order = ["frame_1.png", "frame_10.png", "frame_2.png"]  # the same files, sorted as text
    with pytest.raises(
        DataError,
        match=r"gt.csv, line 3: query 1 is 'frame_2.png' in the ground truth but "
        r"'frame_10.png' in /q; .*other images, or in another order",
    ):
        back.check_names([f"/q/{n}" for n in text_order], [f"/r/{n}" for n in names])
    with pytest.raises(
        DataError, match=r"line 3: reference 1 is 'frame_2.png' in the ground truth but " r"'frame_10.png' in /r"
    ):
        back.check_names([f"/q/{n}" for n in names], [f"/r/{n}" for n in text_order])
    with pytest.raises(DataError, match="has rows for 3 queries but /q has 4 query images"):
        back.check_names([f"/q/{n}" for n in [*names, "frame_11.png"]], [f"/r/{n}" for n in names])


@pytest.mark.parametrize(
    "body, message",
    [
        ("0,1,a.png\n", "line 2: expected 4 columns"),
        ("0,1 2,a.png,r1.png\n", "line 2: 2 reference indices but 1 reference names"),
    ],
)
def test_named_csv_errors(tmp_path, body, message):
    path = tmp_path / "gt.csv"
    path.write_text("query_index,reference_indices,query_name,reference_names\n" + body)
    with pytest.raises(DataError, match=message):
        GroundTruth.from_csv(path)


def test_correct_mask_dense_subset_summary():
    gt = GroundTruth([np.array([0, 1]), np.array([3]), np.array([], dtype=np.int64)], num_references=4)
    mask = gt.correct_mask(np.array([[1, 2], [2, 3], [0, 1]]))
    assert mask.tolist() == [[True, False], [False, True], [False, False]]
    assert gt.correct_mask(np.array([0, 0, 0])).shape == (3, 1)
    with pytest.raises(DataError, match="3 queries but 2 were matched"):
        gt.correct_mask(np.array([[0], [1]]))
    assert gt.dense().sum() == 3 and gt.dense()[1, 3]
    assert gt.is_correct(0, 1) and not gt.is_correct(1, 2)
    sub = gt.subset(query_indices=[1, 0], reference_indices=[3, 1])
    assert _lists(sub) == [[0], [1]] and sub.num_references == 2
    s = gt.summary()
    assert s["queries_with_match"] == 2 and s["mean_matches_per_query"] == pytest.approx(1.0)


def test_real_corridor_ground_truth():
    root = require_shared("corridor")
    gt = GroundTruth.from_csv(root / "ground_truth.csv", num_references=111, num_queries=111)
    assert gt.num_queries == 111 and gt.has_match.all()
    assert _lists(gt)[:2] == [[0, 1, 2], [0, 1, 2, 3]]
    # Every query's own index is among its correct references (the traverses are aligned).
    assert all(q in p for q, p in enumerate(_lists(gt)))


def test_names_a_spreadsheet_would_run_are_quoted_and_read_back_as_they_are(tmp_path):
    gt = GroundTruth([np.array([0, 1]), np.array([2])], num_references=3)
    path = tmp_path / "gt.csv"
    queries, references = ["=q.png", "'quoted.png"], ["-r0.png", "@r1.png", "r2.png"]
    gt.to_csv(path, query_names=queries, reference_names=references)
    assert path.read_text().splitlines()[1:] == ["0,0 1,'=q.png,'-r0.png/@r1.png", "1,2,''quoted.png,r2.png"]
    back = GroundTruth.from_csv(path, num_references=3, num_queries=2)
    back.check_names([f"/q/{n}" for n in queries], [f"/r/{n}" for n in references])
