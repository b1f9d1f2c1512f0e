"""Options every command that takes --method shares; here --fit / --fit-frames (what dbow and
trunk-whitened learn from) through `fdnet evaluate`, `fdnet database build` and `fdnet match`,
and their errors."""

from __future__ import annotations

import json

import pytest

from fdnet.cli import main

from conftest import write_day_night_route

SMALL = [
    "--method-set",
    "trunk-whitened:block=4",
    "--method-set",
    "trunk-whitened:input_size=[32,64]",
    "--method-set",
    "trunk-whitened:bf16=false",
    "--workers",
    "0",
]


@pytest.fixture
def route(tmp_path):
    return write_day_night_route(tmp_path, 8)


def _evaluate(route, tmp_path, *extra):
    out = tmp_path / "result.json"
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(route),
                "--reference",
                "day",
                "--query",
                "night",
                "--frames",
                "4:8",
                "--method",
                "trunk-whitened",
                *SMALL,
                "--json",
                str(out),
                *extra,
            ]
        )
        == 0
    )
    return json.loads(out.read_text())["results"][0]["settings"]  # one method: the result's own object


def test_fit_folder_and_frames_are_recorded_in_the_output(route, tmp_path):
    settings = _evaluate(
        route, tmp_path, "--fit", str(route), "--fit-frames", "0:4", "--method-set", "trunk-whitened:dim=5"
    )
    assert settings["dim"] == 5 and settings["fit_frames"] == "0:4"
    assert "frames 0:4: 8 images of day (4), night (4)" in settings["fitted_on"]


def test_without_fit_it_learns_from_the_references_and_says_so(route, tmp_path):
    settings = _evaluate(route, tmp_path, "--method-set", "trunk-whitened:dim=3")
    assert settings["fitted_on"] == "reference images (4)" and settings["fit"] is None


def _error(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def test_bad_fit_input_is_a_command_error(route, tmp_path, capsys):
    base = [
        "evaluate",
        "--data",
        str(route),
        "--reference",
        "day",
        "--query",
        "night",
        "--frames",
        "4:8",
        "--method",
        "trunk-whitened",
        *SMALL,
    ]
    empty = tmp_path / "empty"
    (empty / "day").mkdir(parents=True)
    err = _error(capsys, [*base, "--fit", str(empty)])
    assert err.startswith("fdnet evaluate: error: trunk-whitened: --fit ") and "no images to fit on" in err
    err = _error(capsys, [*base, "--method-set", "trunk-whitened:dim=2000"])
    assert "fdnet evaluate: error: trunk-whitened: L = dim 2000 is larger than the map" in err
    err = _error(capsys, [*base, "--fit", str(route), "--fit-frames", "0:2", "--method-set", "trunk-whitened:dim=8"])
    assert "fdnet evaluate: error:" in err and "more than 4 fitting images allow (at most 3" in err
    # more L than the references allow, when it learns from them
    err = _error(capsys, [*base, "--method-set", "trunk-whitened:dim=6"])
    assert "fdnet evaluate: error: trunk-whitened: L = 6 dimensions, but 4 fitting vectors" in err
    err = _error(
        capsys,
        [
            "evaluate",
            "--data",
            str(route),
            "--reference",
            "day",
            "--query",
            "night",
            "--method",
            "trunk",
            "--fit",
            str(route),
        ],
    )
    assert "fdnet evaluate: error: --fit" in err and "none of the methods trunk has a setting fit" in err
    err = _error(capsys, [*base, "--fit-frames", "0:2"])
    assert "fdnet evaluate: error: trunk-whitened: fit_frames (0:2) needs fit=DIR" in err


def test_a_database_rebuilds_the_whitening_from_its_fit_folder(route, tmp_path, capsys):
    db = tmp_path / "places.fdb"
    common = ["--method", "trunk-whitened", *SMALL[:-2], "--method-set", "trunk-whitened:dim=4"]
    err = _error(capsys, ["database", "build", "--images", str(route / "day"), "--db", str(db), *common])
    assert "--fit DIR" in err  # nothing to learn from: refused, since queries could not rebuild it
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(route / "day"),
                "--db",
                str(db),
                *common,
                "--fit",
                str(route),
                "--fit-frames",
                "0:4",
            ]
        )
        == 0
    )
    capsys.readouterr()
    from fdnet.matching.database import PlaceDatabase

    with PlaceDatabase.open(db) as opened:
        assert opened.method_options["fit"] == str(route.resolve()) and opened.method_options["fit_frames"] == "0:4"
        assert "frames 0:4" in opened.method_settings["fitted_on"]
    out = tmp_path / "matches.csv"
    assert main(["database", "query", "--db", str(db), "--images", str(route / "night"), "--out", str(out)]) == 0
    assert out.exists()


def test_match_takes_fit(route, tmp_path, capsys):
    out = tmp_path / "matches.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "day"),
                "--query",
                str(route / "night"),
                "--method",
                "trunk-whitened",
                *SMALL,
                "--method-set",
                "trunk-whitened:dim=4",
                "--fit",
                str(route),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert "learning from" not in capsys.readouterr().out  # the folder, not the references
    assert len(out.read_text().splitlines()) > 8


def test_fit_options_go_to_the_methods_that_take_them():
    """As `fdnet reproduce` passes them: a bare --fit to every method that learns from images,
    METHOD:DIR to that one only; --fit-frames likewise; methods without fit get neither."""
    import argparse

    from fdnet.cli.common import method_options

    args = argparse.Namespace(
        method="trunk,trunk-whitened,dbow",
        weights=[],
        vocabulary=[],
        checkpoint=[],
        fit=["/data/a", "dbow:/data/b"],
        fit_frames=["0:100"],
        method_set=[],
    )
    assert method_options(args, "trunk") == {}
    assert method_options(args, "trunk-whitened") == {"fit": "/data/a", "fit_frames": "0:100"}
    assert method_options(args, "dbow") == {"fit": "/data/b", "fit_frames": "0:100"}


def test_a_method_setting_that_is_not_yaml_is_one_line(tmp_path, capsys):
    from fdnet.data.synthetic import generate_route

    route = generate_route(tmp_path / "route", frames=2, conditions=["summer"], size=(32, 64)).root / "summer"
    assert (
        main(
            [
                "match",
                "--reference",
                str(route),
                "--query",
                str(route),
                "--method",
                "sad",
                "--out",
                str(tmp_path / "m.csv"),
                "--method-set",
                "size=[1,",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: --method-set size: '[1,' is not a valid YAML value (line 1")
