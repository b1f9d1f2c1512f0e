"""`fdnet calibrate`, then `fdnet match --calibration` and `fdnet database query` with it."""

import csv
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from fdnet.cli import main

UNRELATED = (3, 8, 15, 20)


@pytest.fixture
def route(tmp_path):
    """24 places seen twice (map, now); 'now' frames in UNRELATED show other textures (wrong
    best matches), the rest are noisy copies."""
    rng = np.random.default_rng(1)
    root = tmp_path / "route"
    for condition in ("map", "now"):
        (root / condition).mkdir(parents=True)
    for i in range(24):
        place = rng.integers(0, 256, size=(24, 32, 3))
        query = (
            rng.integers(0, 256, size=(24, 32, 3))
            if i in UNRELATED
            else np.clip(place * 0.25 + rng.normal(0, 90, place.shape), 0, 255)
        )
        Image.fromarray(place.astype(np.uint8)).save(root / "map" / f"{i:03d}.png")
        Image.fromarray(query.astype(np.uint8)).save(root / "now" / f"{i:03d}.png")
    return root


def calibrate_args(route, *extra):
    return [
        "calibrate",
        "--data",
        str(route),
        "--reference",
        "map",
        "--query",
        "now",
        "--method",
        "raw",
        "--workers",
        "0",
        *extra,
    ]


def rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_calibrate_then_match_writes_decisions(route, tmp_path, capsys):
    cal = tmp_path / "cal.yaml"
    assert (
        main(
            calibrate_args(
                route, "--accept", "margin", "--accept-set", "radius=1", "--target-precision", "1", "--out", str(cal)
            )
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "reaches precision 1.000" in printed and f"wrote {cal}" in printed
    stored = yaml.safe_load(cal.read_text())
    assert stored["rule"] == "margin" and stored["settings"]["margin"]["radius"] == 1
    assert stored["target_precision"] == 1.0 and stored["precision"] == 1.0 and 0 < stored["recall"] < 1
    assert stored["method"] == "raw" and len(stored["fingerprint"]) == 64
    assert stored["measured_on"]["reference"] == "map" and stored["measured_on"]["tolerance"] == 0
    assert stored["sequence_length"] == 1  # 1 = single images, as everywhere

    out = tmp_path / "matches.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "map"),
                "--query",
                str(route / "now"),
                "--method",
                "raw",
                "--top-k",
                "2",
                "--calibration",
                str(cal),
                "--workers",
                "0",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    written = rows(out)
    assert {"acceptance_score", "accepted"} <= set(written[0])
    accepted = [r for r in written if r["accepted"] == "1"]
    # on the calibration pair itself: exactly the accepted count stored, and all of them right
    assert len(accepted) == stored["accepted"]
    assert all(Path(r["query"]).name == Path(r["reference"]).name for r in accepted)
    assert not any(Path(r["query"]).name == f"{i:03d}.png" for r in accepted for i in UNRELATED)  # new places
    assert len({r["query"] for r in accepted}) == len(accepted)  # at most one per query


def test_calibration_in_run_directory_and_database(route, tmp_path, capsys):
    db = tmp_path / "map.db"
    assert (
        main(
            ["database", "build", "--images", str(route / "map"), "--method", "raw", "--db", str(db), "--workers", "0"]
        )
        == 0
    )
    assert (
        main(
            calibrate_args(
                route, "--accept", "ratio", "--accept-set", "radius=1", "--target-precision", "0.9", "--db", str(db)
            )
        )
        == 0
    )
    capsys.readouterr()
    out = tmp_path / "q.csv"
    assert (
        main(
            [
                "database",
                "query",
                "--db",
                str(db),
                "--images",
                str(route / "now"),
                "--top-k",
                "1",
                "--out",
                str(out),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    assert "using the calibration stored in" in capsys.readouterr().err
    written = rows(out)
    accepted = [r for r in written if r["accepted"] == "1"]
    right = sum(Path(r["query"]).name == Path(r["place"]).name for r in accepted)
    assert accepted and right / len(accepted) >= 0.9

    # --store-in-run needs a run directory given as --checkpoint
    assert main(calibrate_args(route, "--store-in-run")) == 2
    assert "--store-in-run needs the run directory" in capsys.readouterr().err


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--target-precision", "1.5", "--out", "x.yaml"], "--target-precision 1.5: a precision must be in (0, 1]"),
        (["--target-precision", "0", "--out", "x.yaml"], "must be in (0, 1]"),
        (["--accept", "nonsense", "--out", "x.yaml"], "unknown acceptance rule 'nonsense'"),
        (["--accept", "raw,margin", "--out", "x.yaml"], "one rule expression expected"),
        ([], "nothing to store the calibration in"),
        (["--choose", "radius", "--out", "x.yaml"], "expected KEY=V1,V2"),
        (["--accept", "raw", "--choose", "radius=1,2", "--out", "x.yaml"], "rule raw has no setting 'radius'"),
        (["--choose", "radius=[1,2]", "--out", "x.yaml"], "--choose radius=[1: must be an integer >= 0"),
        (["--choose", "radius=1,a", "--out", "x.yaml"], "--choose radius=a: must be an integer >= 0"),
        (["--choose", "radius=1", "--choose", "radius=2", "--out", "x.yaml"], "--choose radius given twice"),
        (["--choose", "radius=1,2", "--accept-set", "margin:radius=3", "--out", "x.yaml"], "either fixed or chosen"),
    ],
)
def test_calibrate_bad_input(route, capsys, extra, message):
    assert main(calibrate_args(route, *extra)) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet calibrate: error: ") and message in err and "Traceback" not in err


def test_a_calibration_from_another_model_is_refused(route, tmp_path, capsys):
    cal = tmp_path / "cal.yaml"
    assert main(calibrate_args(route, "--out", str(cal))) == 0
    capsys.readouterr()
    out = tmp_path / "m.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "map"),
                "--query",
                str(route / "now"),
                "--method",
                "hog",
                "--calibration",
                str(cal),
                "--out",
                str(out),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and "calibrated for method 'raw'" in err and "another model" in err
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "map"),
                "--query",
                str(route / "now"),
                "--method",
                "raw",
                "--sequence-length",
                "3",
                "--calibration",
                str(cal),
                "--out",
                str(out),
            ]
        )
        == 2
    )
    assert "--sequence-length 1, used with 3" in capsys.readouterr().err
    db = tmp_path / "hog.db"
    assert (
        main(
            ["database", "build", "--images", str(route / "map"), "--method", "hog", "--db", str(db), "--workers", "0"]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            [
                "database",
                "query",
                "--db",
                str(db),
                "--images",
                str(route / "now"),
                "--calibration",
                str(cal),
                "--workers",
                "0",
            ]
        )
        == 2
    )
    assert capsys.readouterr().err.startswith("fdnet database: error: ")
    # and calibrating raw into a hog database is refused before any work
    assert main(calibrate_args(route, "--db", str(db))) == 2
    assert "fingerprint mismatch" in capsys.readouterr().err


def test_match_with_an_uncalibrated_rule_writes_its_scores_only(route, tmp_path, capsys):
    out = tmp_path / "m.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "map"),
                "--query",
                str(route / "now"),
                "--method",
                "raw",
                "--top-k",
                "1",
                "--accept",
                "margin",
                "--accept-set",
                "radius=1",
                "--workers",
                "0",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    written = rows(out)
    assert "acceptance_score" in written[0] and "accepted" not in written[0]
    # an unrelated query (wrong best) has a smaller margin than most right ones
    score = {Path(r["query"]).name: float(r["acceptance_score"]) for r in written}
    unrelated = [score[f"{i:03d}.png"] for i in UNRELATED]
    right = [v for k, v in score.items() if int(k[:3]) not in UNRELATED]
    assert np.median(unrelated) < np.median(right)
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "map"),
                "--query",
                str(route / "now"),
                "--method",
                "raw",
                "--accept-set",
                "radius=1",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    assert "--accept-set needs --accept" in capsys.readouterr().err


def test_database_query_with_an_uncalibrated_rule(route, tmp_path, capsys):
    db = tmp_path / "map.db"
    assert (
        main(
            ["database", "build", "--images", str(route / "map"), "--method", "raw", "--db", str(db), "--workers", "0"]
        )
        == 0
    )
    out = tmp_path / "q.csv"
    assert (
        main(
            [
                "database",
                "query",
                "--db",
                str(db),
                "--images",
                str(route / "now"),
                "--top-k",
                "1",
                "--accept",
                "margin",
                "--accept-set",
                "radius=1",
                "--out",
                str(out),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    written = rows(out)
    assert "acceptance_score" in written[0] and "accepted" not in written[0] and len(written) == 24
    capsys.readouterr()
    assert main(["database", "query", "--db", str(db), "--images", str(route / "now"), "--accept", "nope"]) == 2
    assert "unknown acceptance rule 'nope'" in capsys.readouterr().err


def test_calibrate_chooses_the_radius(route, tmp_path, capsys):
    cal = tmp_path / "cal.yaml"
    assert main(calibrate_args(route, "--choose", "radius=0,2", "--out", str(cal))) == 0
    stored = yaml.safe_load(cal.read_text())
    assert [t["radius"] for t in stored["measured_on"]["chosen_from"]] == [0, 2]
    assert stored["settings"]["margin"]["radius"] in (0, 2)
    assert "-> chosen {'radius':" in capsys.readouterr().err


def _tiny_fdnet_run(path, seed):
    import torch

    from fdnet.methods.fdnet.config import preset
    from fdnet.methods.fdnet.model import FDNet
    from fdnet.runs import save_checkpoint

    config = preset("tiny")
    torch.manual_seed(seed)
    save_checkpoint(path, FDNet(config.model).named_parts(), config, state={"step": 1})
    return path


def test_calibration_stored_in_an_fdnet_run_directory(route, tmp_path, capsys):
    run = _tiny_fdnet_run(tmp_path / "run", seed=0)
    assert (
        main(
            [
                "calibrate",
                "--data",
                str(route),
                "--reference",
                "map",
                "--query",
                "now",
                "--method",
                "fdnet",
                "--checkpoint",
                str(run),
                "--device",
                "cpu",
                "--workers",
                "0",
                "--target-precision",
                "0.9",
                "--store-in-run",
            ]
        )
        == 0
    )
    stored = yaml.safe_load((run / "calibration.yaml").read_text())
    assert stored["method"] == "fdnet" and stored["target_precision"] == 0.9
    out = tmp_path / "m.csv"
    match = [
        "match",
        "--reference",
        str(route / "map"),
        "--query",
        str(route / "now"),
        "--method",
        "fdnet",
        "--device",
        "cpu",
        "--workers",
        "0",
        "--out",
        str(out),
    ]
    assert main(match + ["--checkpoint", str(run), "--calibration", str(run)]) == 0
    assert "accepted" in rows(out)[0]
    # other weights (another run): the calibration is refused
    other = _tiny_fdnet_run(tmp_path / "other", seed=1)
    capsys.readouterr()
    assert main(match + ["--checkpoint", str(other), "--calibration", str(run)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and "another model" in err


def test_a_write_failing_after_the_work_keeps_the_calibration(route, tmp_path, capsys, monkeypatch):
    """A full disk at the end: the error names the file, and the calibration is not lost (it goes
    to stdout when no place kept it)."""
    import fdnet.decisions.calibration as calibration_module
    from fdnet.errors import OutputError

    def full_disk(calibration, path):
        raise OutputError(f"{path}: cannot write it (no space left on the device); nothing was written there")

    monkeypatch.setattr(calibration_module, "save_calibration", full_disk)
    out = tmp_path / "cal.yaml"
    assert main(calibrate_args(route, "--out", str(out))) == 2
    captured = capsys.readouterr()
    assert f"fdnet calibrate: error: {out}: cannot write it (no space left" in captured.err
    assert "Traceback" not in captured.err
    kept = yaml.safe_load(captured.out.split("save it as a .yaml file):\n", 1)[1])
    assert kept["format"] == "fdnet-calibration" and kept["method"] == "raw"
    assert not out.exists()


def test_a_required_setting_can_be_the_one_chosen(route, tmp_path, capsys):
    """floor needs min; --choose min=... gives it (it failed as 'floor needs its threshold')."""
    cal = tmp_path / "cal.yaml"
    assert (
        main(
            calibrate_args(
                route,
                "--accept",
                "margin+floor",
                "--choose",
                "min=0.0,0.5",
                "--target-precision",
                "0.8",
                "--out",
                str(cal),
            )
        )
        == 0
    )
    stored = yaml.safe_load(cal.read_text())
    assert stored["rule"] == "margin+floor" and stored["settings"]["floor"]["min"] in (0.0, 0.5)
    assert [c["min"] for c in stored["measured_on"]["chosen_from"]] == [0.0, 0.5]
    assert main(calibrate_args(route, "--accept", "margin+floor", "--choose", "min=x", "--out", str(cal))) == 2
    assert "--choose min=x: must be a number" in capsys.readouterr().err


def test_one_rule_for_a_calibration_stored_in_the_run(tmp_path, capsys, caplog):
    """`calibrate --store-in-run` is what match, database query and loop-closure use when given
    no threshold or calibration (and the database stores none)."""
    import torch

    from fdnet.methods.fdnet.config import preset
    from fdnet.methods.fdnet.model import FDNet
    from fdnet.runs import save_checkpoint

    from conftest import write_random_places

    torch.manual_seed(0)
    config = preset("tiny")
    run = tmp_path / "run"
    save_checkpoint(run, FDNet(config.model).named_parts(), config, state={"step": 1})
    root = tmp_path / "route"
    write_random_places(root / "day", 12, seed=3)
    write_random_places(root / "dusk", 12, seed=3, brightness=0.8)
    assert (
        main(
            [
                "calibrate",
                "--data",
                str(root),
                "--reference",
                "day",
                "--query",
                "dusk",
                "--tolerance",
                "0",
                "--method",
                "fdnet",
                "--checkpoint",
                str(run),
                "--accept",
                "margin",
                "--target-precision",
                "0.5",
                "--store-in-run",
            ]
        )
        == 0
    )
    assert (run / "calibration.yaml").is_file()
    capsys.readouterr()
    out = tmp_path / "m.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(root / "day"),
                "--query",
                str(root / "dusk"),
                "--method",
                "fdnet",
                "--checkpoint",
                str(run),
                "--workers",
                "0",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr()
    assert f"using the calibration stored in the run, {run / 'calibration.yaml'}" in printed.err
    assert "accepted" in out.read_text().splitlines()[0] and "queries accepted by margin" in printed.out
    db = tmp_path / "map.db"
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(root / "day"),
                "--method",
                "fdnet",
                "--checkpoint",
                str(run),
                "--db",
                str(db),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    assert main(["database", "query", "--db", str(db), "--images", str(root / "dusk"), "--workers", "0"]) == 0
    err = capsys.readouterr().err
    # the precision it reached where it was measured and on how many queries, beside its target
    assert "using the calibration stored in the run" in err and "it reached precision" in err
    assert "accepted of 12 queries where it was measured; target 0.5" in err
    with caplog.at_level("INFO"):
        assert (
            main(
                [
                    "loop-closure",
                    "--images",
                    str(root / "dusk"),
                    "--method",
                    "fdnet",
                    "--checkpoint",
                    str(run),
                    "--exclude-last",
                    "2",
                    "--workers",
                    "0",
                    "--out",
                    str(tmp_path / "e.csv"),
                ]
            )
            == 0
        )
    assert "measured on a pair of traverses, not on a loop" in caplog.text
    assert "threshold from" in capsys.readouterr().out
