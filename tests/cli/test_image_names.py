"""One name per image across every output that names images of a run: `fdnet match`, `database
query`, a place database's places, loop-closure events and `evaluate --predictions` all give an
image its absolute path as listed (`fdnet.data.images.image_name`), so they join without scripts."""

import json
import os

import numpy as np
from PIL import Image

from fdnet.cli import main
from fdnet.data.images import image_name

from conftest import read_csv_rows

PLACES = 6


def write_route(folder):
    """PLACES places, then each again darker: frame PLACES + i revisits frame i."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    first = [rng.integers(0, 256, size=(32, 64, 3)) for _ in range(PLACES)]
    for i, image in enumerate(first + [np.clip(im * 0.9 + 10, 0, 255) for im in first]):
        Image.fromarray(image.astype(np.uint8)).save(folder / f"frame_{i:03d}.png")
    return folder


def test_every_output_names_an_image_the_same_way(tmp_path, monkeypatch, capsys):
    route = write_route(tmp_path / "data" / "route")
    link = tmp_path / "data" / "linked"
    link.symlink_to(route, target_is_directory=True)
    monkeypatch.chdir(tmp_path / "data")  # relative arguments: the names are absolute all the same
    expected = {i: str(link / f"frame_{i:03d}.png") for i in range(2 * PLACES)}  # as listed, not resolved
    assert all(image_name(f"linked/frame_{i:03d}.png") == name for i, name in expected.items())

    assert (
        main(
            [
                "match",
                "--reference",
                "linked",
                "--query",
                "linked",
                "--method",
                "raw",
                "--top-k",
                "1",
                "--out",
                str(tmp_path / "m.csv"),
            ]
        )
        == 0
    )
    rows = read_csv_rows(tmp_path / "m.csv")
    assert {int(r["query_index"]): r["query"] for r in rows} == expected
    assert {int(r["reference_index"]): r["reference"] for r in rows} == expected

    db = tmp_path / "map.db"
    assert main(["database", "build", "--images", "linked", "--method", "raw", "--db", str(db)]) == 0
    assert (
        main(
            [
                "database",
                "query",
                "--db",
                str(db),
                "--images",
                "linked",
                "--top-k",
                "1",
                "--out",
                str(tmp_path / "q.csv"),
            ]
        )
        == 0
    )
    rows = read_csv_rows(tmp_path / "q.csv")
    assert {int(r["query_index"]): r["query"] for r in rows} == expected
    assert {int(r["place_index"]): r["place"] for r in rows} == expected

    assert (
        main(
            [
                "loop-closure",
                "--images",
                "linked",
                "--method",
                "raw",
                "--sequence-length",
                "1",
                "--exclude-last",
                "2",
                "--accept",
                "margin",
                "--threshold",
                "0",
                "--out",
                str(tmp_path / "events.csv"),
            ]
        )
        == 0
    )
    events = read_csv_rows(tmp_path / "events.csv")
    assert events and all(r["query"] == expected[int(r["query_index"])] for r in events)
    assert all(r["match"] == expected[int(r["match_index"])] for r in events)

    truth = tmp_path / "gt.csv"
    truth.write_text("".join(f"{i},{i}\n" for i in range(2 * PLACES)))
    assert (
        main(
            [
                "evaluate",
                "--data",
                ".",
                "--reference",
                "linked",
                "--query",
                "linked",
                "--method",
                "raw",
                "--ground-truth",
                str(truth),
                "--predictions",
                "1",
                "--json",
                str(tmp_path / "e.json"),
            ]
        )
        == 0
    )
    predictions = json.loads((tmp_path / "e.json").read_text())["results"][0]["predictions"]
    assert {p["query_index"]: p["query"] for p in predictions} == expected
    assert all(p["top_names"] == [expected[i] for i in p["top"]] for p in predictions)
    assert os.path.realpath(expected[0]) != expected[0]  # the test's link is really one
    capsys.readouterr()
