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
    """Single images unless ``extra`` sets a sequence length (the command's default, 10, needs
    longer routes than these 2 x 10 frames)."""
    single = () if "--sequence-length" in extra else ("--sequence-length", "1")
    return [
        "loop-closure",
        "--images",
        str(route),
        "--method",
        "raw",
        "--exclude-last",
        "3",
        "--accept",
        "margin",
        "--threshold",
        "0.2",
        "--out",
        str(tmp_path / "events.csv"),
        *single,
        *extra,
    ]


def test_events_at_the_revisits_and_an_evaluation(route, tmp_path, capsys):
    truth = GroundTruth([[] for _ in range(PLACES)] + [[i] for i in range(PLACES)], 2 * PLACES)
    truth.to_csv(
        tmp_path / "gt.csv",
        [f"frame_{i:03d}.png" for i in range(2 * PLACES)],
        [f"frame_{i:03d}.png" for i in range(2 * PLACES)],
    )
    assert (
        main(
            args(
                route,
                tmp_path,
                "--jsonl",
                str(tmp_path / "events.jsonl"),
                "--ground-truth",
                str(tmp_path / "gt.csv"),
                "--report",
                str(tmp_path / "report.json"),
                "--db",
                str(tmp_path / "map.db"),
            )
        )
        == 0
    )
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
    # R@1 beside top1_accuracy: the report says why they differ
    assert "top1_accuracy counts every evaluated frame, the first pass included" in report["evaluation"]["note"]
    assert "(of the revisiting frames)" in out
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


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--accept", "best"], "unknown acceptance rule 'best'"),
        (["--accept-set", "margin:radius=-1"], "radius=-1"),
        (["--accept-set", "margin:nonsense=1"], "no setting 'nonsense'"),
        (["--images", "/no/such/folder"], "/no/such/folder: not a folder of images"),
        (["--sequence-length", "1", "--method", "nosuch"], "unknown method 'nosuch'"),
        # it was ignored without a word: there is no calibration for it to choose
        (["--target-precision", "0.9"], "--target-precision needs --calibrate-out"),
    ],
)
def test_bad_input_is_one_line_before_any_frame_is_described(route, tmp_path, capsys, no_describing, extra, message):
    assert main(args(route, tmp_path, *extra)) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet loop-closure: error: ") and message in err
    assert "Traceback" not in err


def test_outputs_must_be_writable(route, tmp_path, capsys, no_describing):
    base = ["loop-closure", "--images", str(route), "--method", "raw", "--exclude-last", "3"]
    (tmp_path / "folder").mkdir()
    assert main(base + ["--accept", "margin", "--threshold", "0.2", "--out", str(tmp_path / "folder")]) == 2
    assert "events CSV path is a directory" in capsys.readouterr().err
    (tmp_path / "other.db").write_text("not a database")
    assert (
        main(
            base
            + [
                "--accept",
                "margin",
                "--threshold",
                "0.2",
                "--out",
                str(tmp_path / "e.csv"),
                "--db",
                str(tmp_path / "other.db"),
            ]
        )
        == 2
    )
    assert "not an fdnet place database" in capsys.readouterr().err


def test_a_database_of_another_model_is_refused(route, tmp_path, capsys):
    db = tmp_path / "hog.db"
    assert main(["database", "build", "--images", str(route), "--method", "hog", "--db", str(db)]) == 0
    capsys.readouterr()
    assert main(args(route, tmp_path, "--db", str(db))) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet loop-closure: error: ") and "fingerprint mismatch" in err


def test_a_calibration_from_another_model_is_refused_before_any_frame_is_described(
    route, tmp_path, capsys, no_describing
):
    from fdnet.decisions.acceptance import parse_acceptance
    from fdnet.decisions.calibration import Calibration, save_calibration
    from fdnet.descriptors.classic import HOGDescriptor

    hog = HOGDescriptor()
    save_calibration(
        Calibration(
            rule="margin",
            settings=parse_acceptance("margin").settings,
            threshold=0.2,
            target_precision=1.0,
            precision=1.0,
            recall=0.5,
            accepted=1,
            num_queries=4,
            method="hog",
            fingerprint=hog.fingerprint(),
        ),
        tmp_path / "hog.yaml",
    )
    assert (
        main(
            [
                "loop-closure",
                "--images",
                str(route),
                "--method",
                "raw",
                "--exclude-last",
                "3",
                "--calibration",
                str(tmp_path / "hog.yaml"),
                "--out",
                str(tmp_path / "e.csv"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet loop-closure: error: ") and "calibrated for method 'hog'" in err
    assert (
        main(
            [
                "loop-closure",
                "--images",
                str(route),
                "--method",
                "raw",
                "--exclude-last",
                "3",
                "--calibration",
                str(tmp_path / "missing.yaml"),
                "--out",
                str(tmp_path / "e.csv"),
            ]
        )
        == 2
    )
    assert "calibration file not found" in capsys.readouterr().err
    assert (
        main(
            [
                "loop-closure",
                "--images",
                str(route),
                "--method",
                "raw",
                "--exclude-last",
                "3",
                "--out",
                str(tmp_path / "e.csv"),
            ]
        )
        == 2
    )
    assert "needs an acceptance threshold" in capsys.readouterr().err


def test_calibrate_on_one_traverse_and_use_it_on_another(tmp_path, capsys):
    truth = GroundTruth([[] for _ in range(PLACES)] + [[i] for i in range(PLACES)], 2 * PLACES)
    truth.to_csv(tmp_path / "gt.csv")
    first, second = write_route(tmp_path / "a", seed=1), write_route(tmp_path / "b", seed=2)
    base = [
        "loop-closure",
        "--method",
        "raw",
        "--exclude-last",
        "3",
        "--sequence-length",
        "1",
        "--ground-truth",
        str(tmp_path / "gt.csv"),
    ]
    assert (
        main(
            base
            + [
                "--images",
                str(first),
                "--accept",
                "margin",
                "--out",
                str(tmp_path / "a.csv"),
                "--calibrate-out",
                str(tmp_path / "cal.yaml"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "0 loop closures in 20 frames" in out  # a calibration run accepts nothing
    assert "reaches precision 1.000 at recall 1.000 on this traverse" in out
    assert read_csv_rows(tmp_path / "a.csv") == []
    assert (
        main(
            base
            + ["--images", str(second), "--calibration", str(tmp_path / "cal.yaml"), "--out", str(tmp_path / "b.csv")]
        )
        == 0
    )
    rows = read_csv_rows(tmp_path / "b.csv")
    # the threshold is the first route's lowest true score: on this route it keeps every closure
    # right and most of them
    assert len(rows) >= PLACES // 2
    assert all(int(r["match_index"]) == int(r["query_index"]) - PLACES for r in rows)
    capsys.readouterr()
    assert (
        main(
            base[:-2]
            + [
                "--images",
                str(first),
                "--accept",
                "margin",
                "--out",
                str(tmp_path / "c.csv"),
                "--calibrate-out",
                str(tmp_path / "c.yaml"),
            ]
        )
        == 2
    )
    assert "needs its ground truth" in capsys.readouterr().err
    assert (
        main(
            base
            + [
                "--images",
                str(first),
                "--accept",
                "margin",
                "--out",
                str(tmp_path / "c.csv"),
                "--calibrate-out",
                str(tmp_path / "c.yaml"),
                "--target-precision",
                "1.5",
            ]
        )
        == 2
    )
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
    assert (
        main(
            [
                "groundtruth",
                "--positions",
                str(tmp_path / "route.csv"),
                str(tmp_path / "route.csv"),
                "--reference",
                str(route),
                "--query",
                str(route),
                "--tolerance-m",
                "5",
                "--out",
                str(tmp_path / "gt.csv"),
            ]
        )
        == 0
    )
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


def write_two_condition_route(root, n=12):
    """root/day and root/dusk: n random-texture places, the same places at dusk (darker, noisier)."""
    rng = np.random.default_rng(4)
    day = [rng.integers(0, 256, size=(32, 64, 3)) for _ in range(n)]
    for condition, images in (
        ("day", day),
        ("dusk", [np.clip(im * 0.8 + rng.normal(0, 10, size=im.shape), 0, 255) for im in day]),
    ):
        (root / condition).mkdir(parents=True)
        for i, image in enumerate(images):
            Image.fromarray(image.astype(np.uint8)).save(root / condition / f"img_{i:03d}.png")
    return root


def test_data_conditions_builds_the_traverse_and_ground_truth_of_a_link_folder(tmp_path, capsys):
    root = write_two_condition_route(tmp_path / "route")
    # the same traverse by hand: a folder of links, day frames 2..9 then dusk frames 2..9
    links = tmp_path / "links"
    links.mkdir()
    for k, (condition, i) in enumerate([("day", i) for i in range(2, 10)] + [("dusk", i) for i in range(2, 10)]):
        (links / f"frame_{k:03d}.png").symlink_to(root / condition / f"img_{i:03d}.png")
    truth = GroundTruth([[] for _ in range(8)] + [[q - 9, q - 8, q - 7] for q in range(8, 16)], 16)
    truth = GroundTruth([[r for r in p if 0 <= r < 8] for p in truth.positives], 16)
    truth.to_csv(tmp_path / "gt.csv")
    common = [
        "--method",
        "raw",
        "--exclude-last",
        "2",
        "--sequence-length",
        "1",
        "--accept",
        "margin",
        "--threshold",
        "0.1",
    ]
    assert (
        main(
            [
                "loop-closure",
                "--images",
                str(links),
                *common,
                "--ground-truth",
                str(tmp_path / "gt.csv"),
                "--out",
                str(tmp_path / "links.csv"),
                "--report",
                str(tmp_path / "links.json"),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "loop-closure",
                "--data",
                str(root),
                "--conditions",
                "day,dusk",
                "--frames",
                "2:10",
                "--tolerance",
                "1",
                *common,
                "--out",
                str(tmp_path / "route.csv"),
                "--report",
                str(tmp_path / "route.json"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    # the first pass's frames with something to search (3..7) and the 8 revisits, in both runs
    # (single images: the seam the route knows of changes no sequence here)
    assert (
        out.count(
            "first pass (no place seen before): 5 frames, 1 closures accepted (all false); revisits: 8 "
            "frames, 8 closed right"
        )
        == 2
    )
    by_links, by_route = read_csv_rows(tmp_path / "links.csv"), read_csv_rows(tmp_path / "route.csv")
    assert len(by_route) >= 6
    # the same closures; a margin may differ where the link folder's walk back crossed into the day
    # frames (the route's stops at the seam, so a different place is the best one outside), and the
    # similarity: the route knows its two recordings, so a dusk frame's similarity to a day place is
    # taken relative to its level against the day frames, the link folder's is not
    key = ("query_index", "match_index")
    assert [tuple(r[k] for k in key) for r in by_links] == [tuple(r[k] for k in key) for r in by_route]
    pairs = [(float(a["similarity"]), float(b["similarity"])) for a, b in zip(by_links, by_route)]
    # up to the first dusk frame (8) the map holds the day recording alone: nothing changes
    one_recording = [int(r["query_index"]) <= 8 for r in by_route]
    assert all(a == b for (a, b), first in zip(pairs, one_recording) if first)
    assert all(a > b for (a, b), first in zip(pairs, one_recording) if not first) and not all(one_recording)
    # the places are named by the files listed: the links' own names, the route's files
    assert all("/links/frame_" in r["query"] for r in by_links)
    assert all(
        "/route/dusk/img_" in r["query"] and "/route/day/img_" in r["match"]
        for r in by_route
        if int(r["query_index"]) >= 8
    )
    links_eval = json.loads((tmp_path / "links.json").read_text())["evaluation"]
    route_eval = json.loads((tmp_path / "route.json").read_text())["evaluation"]
    assert links_eval["at_threshold"] == route_eval["at_threshold"]
    assert links_eval["metrics"]["recall_at_n"] == route_eval["metrics"]["recall_at_n"]
    assert json.loads((tmp_path / "route.json").read_text())["recent_past"]["segments"] == 2


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--conditions", "day"], "--conditions needs at least two conditions"),
        (["--conditions", "day,day"], "names a condition twice"),
        (["--conditions", "day,night"], "condition folder not found"),
        (["--conditions", "day,dusk", "--gate", "min_brightness=3"], "min_brightness must be in [0, 1]"),
        (["--conditions", "day,dusk", "--gate", "consistency=0"], "consistency must be a whole number of at least 1"),
        (["--conditions", "day,dusk", "--gate", "colour=1"], "unknown loop gate setting 'colour'"),
        (["--conditions", "day,dusk", "--frames", "50:60"], "no frames in the range 50:60"),
        ([], "--data needs --conditions"),
    ],
)
def test_bad_route_and_gate_settings_are_one_line(tmp_path, capsys, no_describing, extra, message):
    root = write_two_condition_route(tmp_path / "route")
    assert (
        main(
            [
                "loop-closure",
                "--data",
                str(root),
                "--method",
                "raw",
                "--exclude-last",
                "2",
                "--accept",
                "margin",
                "--threshold",
                "0.1",
                "--out",
                str(tmp_path / "e.csv"),
                *extra,
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet loop-closure: error: ") and message in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_images_with_route_flags_is_refused(route, tmp_path, capsys, no_describing):
    assert main(args(route, tmp_path, "--conditions", "a,b")) == 2
    assert "--conditions go with --data DIR" in capsys.readouterr().err


def test_defaults_use_the_loop_calibration_stored_in_the_run_directory(tmp_path, capsys):
    """--calibrate-out RUN_DIR writes RUN_DIR/loop-calibration.yaml; a later run with only
    --images, --method, --checkpoint and --exclude-last uses its rule, sequence length and threshold."""
    from fdnet.decisions import loop_closure

    root = write_two_condition_route(tmp_path / "route", n=30)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    calibrated = run_dir / loop_closure.LOOP_CALIBRATION_FILE
    # raw takes no checkpoint: stand in for a trained method's run directory by pointing the
    # lookup at it, as --checkpoint RUN_DIR does
    assert (
        main(
            [
                "loop-closure",
                "--data",
                str(root),
                "--conditions",
                "day,dusk",
                "--tolerance",
                "1",
                "--method",
                "raw",
                "--exclude-last",
                "2",
                "--sequence-length",
                "3",
                "--calibrate-out",
                str(run_dir),
                "--out",
                str(tmp_path / "cal.csv"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert f"wrote {calibrated}" in out
    from fdnet.decisions.calibration import load_calibration

    stored = load_calibration(calibrated)
    assert stored.rule == "margin" and stored.sequence_length == 3 and stored.measured_on["loop_closure"]
    assert stored.measured_on["gates"]["still_difference"] == 0.04
    assert (
        main(
            [
                "loop-closure",
                "--images",
                str(root / "dusk"),
                "--method",
                "raw",
                "--exclude-last",
                "2",
                "--calibration",
                str(calibrated),
                "--out",
                str(tmp_path / "e.csv"),
            ]
        )
        == 0
    )
    assert "sequences of 3, threshold from" in capsys.readouterr().out
    # gates other than those it was measured with are refused
    assert (
        main(
            [
                "loop-closure",
                "--images",
                str(root / "dusk"),
                "--method",
                "raw",
                "--exclude-last",
                "2",
                "--calibration",
                str(calibrated),
                "--gate",
                "consistency=3",
                "--out",
                str(tmp_path / "e.csv"),
            ]
        )
        == 2
    )
    assert "was measured with loop gates consistency=1" in capsys.readouterr().err


def test_a_pair_calibration_used_in_loop_closure_is_warned_about(route, tmp_path, capsys, caplog):
    from fdnet.decisions.acceptance import parse_acceptance
    from fdnet.decisions.calibration import Calibration, save_calibration

    raw = RawThumbnail()
    save_calibration(
        Calibration(
            rule="margin",
            settings=parse_acceptance("margin").settings,
            threshold=0.2,
            target_precision=1.0,
            precision=1.0,
            recall=0.5,
            accepted=7,
            num_queries=40,
            method="raw",
            fingerprint=raw.fingerprint(),
            measured_on={"reference": "day"},
        ),
        tmp_path / "pair.yaml",
    )
    with caplog.at_level("INFO"):
        assert (
            main(
                [
                    "loop-closure",
                    "--images",
                    str(route),
                    "--method",
                    "raw",
                    "--exclude-last",
                    "3",
                    "--calibration",
                    str(tmp_path / "pair.yaml"),
                    "--out",
                    str(tmp_path / "e.csv"),
                ]
            )
            == 0
        )
    text = caplog.text
    assert "measured on a pair of traverses, not on a loop" in text
    assert "on 7 accepted of 40 frames" in text


def test_ground_truth_without_a_searchable_revisit_is_refused_before_any_frame(route, tmp_path, capsys, no_describing):
    # every frame's true place is its previous frame: always inside --exclude-last 3
    truth = GroundTruth([[]] + [[q - 1] for q in range(1, 2 * PLACES)], 2 * PLACES)
    truth.to_csv(tmp_path / "gt.csv")
    db = tmp_path / "map.db"
    assert main(args(route, tmp_path, "--ground-truth", str(tmp_path / "gt.csv"), "--db", str(db))) == 2
    err = capsys.readouterr().err
    assert "no frame of the traverse revisits a place it could search" in err
    # nothing was stored: the same database takes the run with the right ground truth
    if db.exists():
        from fdnet.matching.database import PlaceDatabase

        with PlaceDatabase.open(db) as stored:
            assert len(stored) == 0


def test_an_event_the_disk_cannot_hold_leaves_no_half_line(tmp_path, monkeypatch):
    import errno
    import os

    from fdnet.decisions.loop_closure import Closure
    from fdnet.decisions.loop_events import EventLog
    from fdnet.errors import OutputError

    closure = Closure(3, "q.png", 0, "p.png", 0.5, 0.9, "margin", 0.1)
    with EventLog(tmp_path / "e.csv") as log:
        log.write(closure)
        whole = (tmp_path / "e.csv").read_bytes()
        real_write = os.write

        def full_disk(fd, data):
            if len(data) > 10:
                return real_write(fd, data[:10])  # the disk takes 10 bytes ...
            raise OSError(errno.ENOSPC, "No space left on device")  # ... then is full

        monkeypatch.setattr(os, "write", full_disk)
        with pytest.raises(OutputError, match="No space left on device.*ends at the last whole event") as caught:
            log.write(closure)
        assert caught.value.errno == errno.ENOSPC
    assert (tmp_path / "e.csv").read_bytes() == whole


def test_a_read_only_database_is_refused_before_any_frame(route, tmp_path, capsys, make_read_only, monkeypatch):
    folder = tmp_path / "maps"
    folder.mkdir()
    db = folder / "map.db"
    assert main(["database", "build", "--images", str(route), "--method", "raw", "--db", str(db)]) == 0
    make_read_only(folder)
    capsys.readouterr()

    def describe(self, images):
        raise AssertionError("images were described before the refusal")

    monkeypatch.setattr(RawThumbnail, "describe", describe)
    assert main(args(route, tmp_path, "--db", str(db))) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet loop-closure: error: ") and str(db) in err and "read-only" in err.lower()


def test_what_a_failed_create_left_is_reused(route, tmp_path, capsys):
    import sqlite3

    db = tmp_path / "map.db"
    with sqlite3.connect(db) as conn:  # a SQLite file without tables, as a killed create leaves it
        conn.execute("CREATE TABLE scratch (x)")
        conn.execute("DROP TABLE scratch")
    assert db.stat().st_size > 0
    (tmp_path / "empty.db").write_bytes(b"")
    for path in (db, tmp_path / "empty.db"):
        assert main(args(route, tmp_path, "--db", str(path))) == 0
        assert "10 loop closures in 20 frames" in capsys.readouterr().out


def test_an_event_one_file_cannot_hold_is_taken_out_of_the_other(tmp_path, monkeypatch):
    """The CSV took the event, the JSON lines' disk was full: both files end at the last event
    acknowledged (a real 1 MiB tmpfs gave a CSV with one event more than its JSON lines)."""
    import errno
    import os

    from fdnet.decisions.loop_closure import Closure
    from fdnet.decisions.loop_events import EventLog
    from fdnet.errors import OutputError

    closure = Closure(3, "q.png", 0, "p.png", 0.5, 0.9, "margin", 0.1)
    with EventLog(tmp_path / "e.csv", tmp_path / "e.jsonl") as log:
        log.write(closure)
        before = (tmp_path / "e.csv").read_bytes(), (tmp_path / "e.jsonl").read_bytes()
        real_write = os.write
        jsonl_fd = log._fds[1]

        def jsonl_disk_full(fd, data):
            if fd == jsonl_fd:
                raise OSError(errno.ENOSPC, "No space left on device")
            return real_write(fd, data)

        monkeypatch.setattr(os, "write", jsonl_disk_full)
        with pytest.raises(OutputError, match="e.jsonl: cannot write the loop-closure event"):
            log.write(closure)
    assert ((tmp_path / "e.csv").read_bytes(), (tmp_path / "e.jsonl").read_bytes()) == before


def test_no_frame_count_needed_and_closures_carry_p_correct(tmp_path, capsys):
    """Without --exclude-last the recent past comes from the traverse (the report says how far
    back); a calibration's p_correct fit goes into each event; --calibration takes a run directory."""
    root = write_two_condition_route(tmp_path / "route", n=30)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    assert (
        main(
            [
                "loop-closure",
                "--data",
                str(root),
                "--conditions",
                "day,dusk",
                "--tolerance",
                "1",
                "--method",
                "raw",
                "--sequence-length",
                "3",
                "--calibrate-out",
                str(run_dir),
                "--out",
                str(tmp_path / "cal.csv"),
                "--report",
                str(tmp_path / "cal.json"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "recent past excluded: median" in out and "(2 segment(s)" in out
    assert "p_correct fitted on" in out
    report = json.loads((tmp_path / "cal.json").read_text())
    assert report["exclude_last"] == 0 and report["recent_past"]["segments"] == 2
    assert sum(report["recent_past"]["histogram"].values()) == 60
    assert (
        main(
            [
                "loop-closure",
                "--data",
                str(root),
                "--conditions",
                "day,dusk",
                "--tolerance",
                "1",
                "--method",
                "raw",
                "--calibration",
                str(run_dir),
                "--out",
                str(tmp_path / "events.csv"),
            ]
        )
        == 0
    )
    rows = read_csv_rows(tmp_path / "events.csv")
    assert rows and all(0.0 < float(r["p_correct"]) < 1.0 for r in rows)


def test_a_run_unlike_its_calibration_loop_says_so(tmp_path, capsys):
    """Vectors computed elsewhere (--method precomputed): a calibration made on one kind of route
    and used on a route whose wrong candidates stand out more prints a warning naming both."""
    from PIL import Image

    from fdnet.data.groundtruth import GroundTruth
    from tests.decisions.test_loop_recency import slow_route

    rng = np.random.default_rng(0)
    names, vectors = [], []
    for folder, persistence in (("calibration", 0.93), ("slower", 0.97)):
        (tmp_path / folder).mkdir()
        first, second = slow_route(n=150, seed=5 if folder == "slower" else 0, persistence=persistence)
        for i, vector in enumerate(np.concatenate([first, second])):
            path = tmp_path / folder / f"frame_{i:03d}.png"
            Image.fromarray(rng.integers(0, 256, size=(32, 64, 3)).astype(np.uint8)).save(path)
            names.append(str(path))
            vectors.append(vector)
    np.savez(tmp_path / "vectors.npz", names=np.array(names), descriptors=np.array(vectors, np.float32))
    GroundTruth(
        [[] for _ in range(150)] + [[q - 151, q - 150, q - 149] if q > 150 else [0, 1] for q in range(150, 300)], 300
    ).to_csv(tmp_path / "gt.csv")
    common = ["--method", "precomputed", "--vectors", str(tmp_path / "vectors.npz"), "--workers", "0", "--no-progress"]
    assert (
        main(
            [
                "loop-closure",
                "--images",
                str(tmp_path / "calibration"),
                *common,
                "--ground-truth",
                str(tmp_path / "gt.csv"),
                "--calibrate-out",
                str(tmp_path / "cal.yaml"),
                "--out",
                str(tmp_path / "cal.csv"),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            [
                "loop-closure",
                "--images",
                str(tmp_path / "slower"),
                *common,
                "--calibration",
                str(tmp_path / "cal.yaml"),
                "--out",
                str(tmp_path / "events.csv"),
            ]
        )
        == 0
    )
    captured = capsys.readouterr()
    assert f"scores rejected on {tmp_path / 'slower'}" in captured.out and str(tmp_path / "cal.yaml") in captured.out
    assert "stand out more" in captured.err


def test_a_resumed_run_says_how_many_frames_it_took_over(route, tmp_path, capsys):
    """The frames an interrupted run stored are replayed, and the summary says so (they are part
    of this traverse, not places from before it)."""
    partial = tmp_path / "partial"
    partial.mkdir()
    frames = sorted(route.iterdir())
    for path in frames[:12]:  # the run was killed after storing its first 12 frames
        (partial / path.name).write_bytes(path.read_bytes())
    common = [
        "loop-closure",
        "--images",
        str(partial),
        "--method",
        "raw",
        "--sequence-length",
        "1",
        "--accept",
        "margin",
        "--threshold",
        "0.2",
        "--db",
        str(tmp_path / "map.db"),
        "--no-progress",
        "--workers",
        "0",
    ]
    assert main([*common, "--out", str(tmp_path / "first.csv")]) == 0
    for path in frames[12:]:
        (partial / path.name).write_bytes(path.read_bytes())
    capsys.readouterr()
    assert main([*common, "--resume", "--out", str(tmp_path / "events.csv")]) == 0
    out = capsys.readouterr().out
    assert (
        f"{tmp_path / 'map.db'}: 0 places before this traverse, {len(frames)} after (12 of its frames stored by "
        "the interrupted run, replayed, not added again)"
    ) in out


def test_a_second_run_on_the_same_events_is_refused_before_it_touches_anything(route, tmp_path, capsys):
    """Two `--resume` runs at once: the loser must not cut the events back after the winner wrote.
    Each run holds a lock on its events files and database; a second is one line naming the holder."""
    from fdnet.runs.lock import RunLock

    common = [
        "loop-closure",
        "--images",
        str(route),
        "--method",
        "raw",
        "--sequence-length",
        "1",
        "--accept",
        "margin",
        "--threshold",
        "0.2",
        "--db",
        str(tmp_path / "map.db"),
        "--no-progress",
        "--workers",
        "0",
        "--out",
        str(tmp_path / "events.csv"),
    ]
    assert main(common) == 0
    capsys.readouterr()
    events = (tmp_path / "events.csv").read_bytes()
    database = (tmp_path / "map.db").read_bytes()
    with RunLock.for_file(tmp_path / "events.csv", "fdnet loop-closure (the first run)"):
        assert main([*common, "--resume"]) == 2
        err = capsys.readouterr().err
        assert f"{tmp_path / 'events.csv'} is in use by process" in err and "(the first run)" in err, err
        assert len(err.strip().splitlines()) == 1
        assert (tmp_path / "events.csv").read_bytes() == events and (tmp_path / "map.db").read_bytes() == database
    with RunLock.for_file(tmp_path / "map.db", "fdnet loop-closure (the first run)"):
        assert main([*common, "--resume"]) == 2
        assert f"{tmp_path / 'map.db'} is in use by process" in capsys.readouterr().err
    assert main([*common, "--resume"]) == 0  # once the first run has ended
