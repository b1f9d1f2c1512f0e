"""`fdnet loop-closure` on a made-up route that revisits its places."""

import json

import numpy as np
import pytest
from PIL import Image

from fdnet.cli import main
from fdnet.data.groundtruth import GroundTruth
from fdnet.descriptors.classic import RawThumbnail

from conftest import read_csv_rows

PLACES = 10


def write_route(folder, seed=0):
    """PLACES random-texture places, then each again (noisier, darker) in the same order:
    frame PLACES + i revisits frame i."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    first = [rng.integers(0, 256, size=(32, 64, 3)) for _ in range(PLACES)]
    again = [np.clip(im * 0.9 + 10 + rng.normal(0, 12, size=im.shape), 0, 255) for im in first]
    for i, image in enumerate(first + again):
        Image.fromarray(image.astype(np.uint8)).save(folder / f"frame_{i:03d}.png")
    return folder


@pytest.fixture
def route(tmp_path):
    return write_route(tmp_path / "route")


def args(route, tmp_path, *extra):
    return ["loop-closure", "--images", str(route), "--method", "raw", "--exclude-last", "3", "--accept", "margin",
            "--threshold", "0.2", "--out", str(tmp_path / "events.csv"), *extra]


def test_events_at_the_revisits_and_an_evaluation(route, tmp_path, capsys):
    truth = GroundTruth([[] for _ in range(PLACES)] + [[i] for i in range(PLACES)], 2 * PLACES)
    truth.to_csv(tmp_path / "gt.csv", [f"frame_{i:03d}.png" for i in range(2 * PLACES)],
                 [f"frame_{i:03d}.png" for i in range(2 * PLACES)])
    assert main(args(route, tmp_path, "--jsonl", str(tmp_path / "events.jsonl"), "--ground-truth",
                     str(tmp_path / "gt.csv"), "--report", str(tmp_path / "report.json"), "--db",
                     str(tmp_path / "map.db"))) == 0
    out = capsys.readouterr().out
    rows = read_csv_rows(tmp_path / "events.csv")
    assert [int(r["query_index"]) for r in rows] == list(range(PLACES, 2 * PLACES))
    assert [int(r["match_index"]) for r in rows] == list(range(PLACES))
    assert [r["match"].rsplit("/", 1)[1] for r in rows] == [f"frame_{i:03d}.png" for i in range(PLACES)]
    assert {r["rule"] for r in rows} == {"margin"}
    events = [json.loads(line) for line in (tmp_path / "events.jsonl").read_text().splitlines()]
    assert [e["match_index"] for e in events] == list(range(PLACES))
    assert "10 loop closures in 20 frames" in out and "frames/s" in out
    assert "R@100P 1.000" in out and "10 accepted, 10 true, 0 false" in out
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["evaluation"]["metrics"]["recall_at_100_precision"] == 1.0
    assert report["places_after"] == 2 * PLACES


def test_a_second_session_closes_loops_against_the_first_sessions_database(tmp_path, capsys):
    route = write_route(tmp_path / "all")
    day1, day2 = tmp_path / "day1", tmp_path / "day2"
    day1.mkdir()
    day2.mkdir()
    for i in range(2 * PLACES):
        (route / f"frame_{i:03d}.png").rename((day1 if i < PLACES else day2) / f"frame_{i:03d}.png")
    db = tmp_path / "map.db"
    assert main(["database", "build", "--images", str(day1), "--method", "raw", "--db", str(db)]) == 0
    assert main(args(day2, tmp_path, "--db", str(db))) == 0
    rows = read_csv_rows(tmp_path / "events.csv")
    # the first frame of day 2 already closes a loop: day 1's places are not this traverse's last frames
    assert [int(r["query_index"]) for r in rows] == list(range(PLACES))
    assert [int(r["match_index"]) for r in rows] == list(range(PLACES))
    # running day 2 again into the same database is refused, not added twice
    capsys.readouterr()
    assert main(args(day2, tmp_path, "--db", str(db))) == 2
    assert "already holds 10 of these 10 frames" in capsys.readouterr().err


@pytest.fixture
def no_describing(monkeypatch):
    def describe(self, images):
        raise AssertionError("images were described before the refusal")

    monkeypatch.setattr(RawThumbnail, "describe", describe)


@pytest.mark.parametrize("extra, message", [
    (["--accept", "best"], "unknown acceptance rule 'best'"),
    (["--accept-set", "margin:radius=-1"], "radius=-1"),
    (["--accept-set", "margin:nonsense=1"], "no setting 'nonsense'"),
    (["--images", "/no/such/folder"], "/no/such/folder: not a folder of images"),
    (["--sequence-length", "1", "--method", "nosuch"], "unknown method 'nosuch'"),
])
def test_bad_input_is_one_line_before_any_frame_is_described(route, tmp_path, capsys, no_describing, extra, message):
    assert main(args(route, tmp_path, *extra)) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet loop-closure: error: ") and message in err
    assert "Traceback" not in err


def test_threshold_needs_a_rule_and_outputs_must_be_writable(route, tmp_path, capsys, no_describing):
    base = ["loop-closure", "--images", str(route), "--method", "raw", "--exclude-last", "3"]
    assert main(base + ["--threshold", "0.2", "--out", str(tmp_path / "e.csv")]) == 2
    assert "--threshold needs --accept RULE" in capsys.readouterr().err
    (tmp_path / "folder").mkdir()
    assert main(base + ["--accept", "margin", "--threshold", "0.2", "--out", str(tmp_path / "folder")]) == 2
    assert "events CSV path is a directory" in capsys.readouterr().err
    (tmp_path / "other.db").write_text("not a database")
    assert main(base + ["--accept", "margin", "--threshold", "0.2", "--out", str(tmp_path / "e.csv"),
                        "--db", str(tmp_path / "other.db")]) == 2
    assert "not an fdnet place database" in capsys.readouterr().err


def test_a_database_of_another_model_is_refused(route, tmp_path, capsys):
    db = tmp_path / "hog.db"
    assert main(["database", "build", "--images", str(route), "--method", "hog", "--db", str(db)]) == 0
    capsys.readouterr()
    assert main(args(route, tmp_path, "--db", str(db))) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet loop-closure: error: ") and "fingerprint mismatch" in err


def test_a_calibration_from_another_model_is_refused_before_any_frame_is_described(route, tmp_path, capsys,
                                                                                   no_describing):
    from fdnet.decisions.acceptance import parse_acceptance
    from fdnet.decisions.calibration import Calibration, save_calibration
    from fdnet.descriptors.classic import HOGDescriptor

    hog = HOGDescriptor()
    save_calibration(Calibration(rule="margin", settings=parse_acceptance("margin").settings, threshold=0.2,
                                 target_precision=1.0, precision=1.0, recall=0.5, accepted=1, num_queries=4,
                                 method="hog", fingerprint=hog.fingerprint()), tmp_path / "hog.yaml")
    assert main(["loop-closure", "--images", str(route), "--method", "raw", "--exclude-last", "3", "--calibration",
                 str(tmp_path / "hog.yaml"), "--out", str(tmp_path / "e.csv")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet loop-closure: error: ") and "calibrated for method 'hog'" in err
    assert main(["loop-closure", "--images", str(route), "--method", "raw", "--exclude-last", "3", "--calibration",
                 str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "e.csv")]) == 2
    assert "calibration file not found" in capsys.readouterr().err
    assert main(["loop-closure", "--images", str(route), "--method", "raw", "--exclude-last", "3", "--out",
                 str(tmp_path / "e.csv")]) == 2
    assert "needs an acceptance threshold" in capsys.readouterr().err


def test_calibrate_on_one_traverse_and_use_it_on_another(tmp_path, capsys):
    truth = GroundTruth([[] for _ in range(PLACES)] + [[i] for i in range(PLACES)], 2 * PLACES)
    truth.to_csv(tmp_path / "gt.csv")
    first, second = write_route(tmp_path / "a", seed=1), write_route(tmp_path / "b", seed=2)
    base = ["loop-closure", "--method", "raw", "--exclude-last", "3", "--ground-truth", str(tmp_path / "gt.csv")]
    assert main(base + ["--images", str(first), "--accept", "margin", "--out", str(tmp_path / "a.csv"),
                        "--calibrate-out", str(tmp_path / "cal.yaml")]) == 0
    out = capsys.readouterr().out
    assert "0 loop closures in 20 frames" in out  # a calibration run accepts nothing
    assert "reaches precision 1.000 at recall 1.000 on this traverse" in out
    assert read_csv_rows(tmp_path / "a.csv") == []
    assert main(base + ["--images", str(second), "--calibration", str(tmp_path / "cal.yaml"),
                        "--out", str(tmp_path / "b.csv")]) == 0
    rows = read_csv_rows(tmp_path / "b.csv")
    # the threshold is the first route's lowest true score: on this route it keeps every closure
    # right and most of them
    assert len(rows) >= PLACES // 2
    assert all(int(r["match_index"]) == int(r["query_index"]) - PLACES for r in rows)
    capsys.readouterr()
    assert main(base[:-2] + ["--images", str(first), "--accept", "margin", "--out", str(tmp_path / "c.csv"),
                             "--calibrate-out", str(tmp_path / "c.yaml")]) == 2
    assert "needs its ground truth" in capsys.readouterr().err
    assert main(base + ["--images", str(first), "--accept", "margin", "--out", str(tmp_path / "c.csv"),
                        "--calibrate-out", str(tmp_path / "c.yaml"), "--target-precision", "1.5"]) == 2
    assert "must be in (0, 1]" in capsys.readouterr().err


def test_verification_refuses_thumbnails_before_any_frame_is_described(route, tmp_path, capsys, no_describing):
    assert main(args(route, tmp_path, "--accept", "margin+verified")) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet loop-closure: error: ") and "too small for geometric verification" in err


def test_ground_truth_from_positions_with_fdnet_groundtruth(route, tmp_path, capsys):
    # the robot drives PLACES places 20 m apart, then the same places again
    with open(tmp_path / "route.csv", "w") as fh:
        fh.write("image,easting,northing\n")
        for i in range(2 * PLACES):
            fh.write(f"frame_{i:03d}.png,{20.0 * (i % PLACES)},0\n")
    assert main(["groundtruth", "--positions", str(tmp_path / "route.csv"), str(tmp_path / "route.csv"),
                 "--reference", str(route), "--query", str(route), "--tolerance-m", "5",
                 "--out", str(tmp_path / "gt.csv")]) == 0
    capsys.readouterr()
    assert main(args(route, tmp_path, "--ground-truth", str(tmp_path / "gt.csv"))) == 0
    out = capsys.readouterr().out
    # each frame's own position is cut (never searchable): only the second pass revisits
    assert "10 revisiting a searchable place: R@100P 1.000" in out
    assert "10 accepted, 10 true, 0 false (precision 1.000, recall 1.000)" in out


def test_a_name_that_is_not_utf8_is_refused_before_any_frame_is_described(route, tmp_path, capsys, monkeypatch):
    import os

    os.rename(route / "frame_015.png", os.path.join(os.fsencode(route), b"frame_015\xe9.png"))

    def describe(self, images):
        raise AssertionError("frames were described before the refusal")

    monkeypatch.setattr(RawThumbnail, "describe", describe)
    assert main(args(route, tmp_path)) == 2
    err = capsys.readouterr().err
    assert "frame_015\\xe9.png': the file name is not valid UTF-8, which a place database cannot store" in err
