"""`--method precomputed --vectors FILE`: vectors computed elsewhere, keyed by image
(fdnet.descriptors.precomputed)."""

import json

import numpy as np
import pytest

from fdnet.cli import main
from fdnet.descriptors import create
from fdnet.errors import DataError

from conftest import read_csv_rows, write_random_places


@pytest.fixture
def route(tmp_path):
    """Two conditions of the same 10 places whose files share their names (day/frame_000.png,
    dusk/frame_000.png, ...), as every multi-condition dataset's do."""
    root = tmp_path / "route"
    write_random_places(root / "day", 10, seed=4)
    write_random_places(root / "dusk", 10, seed=4, brightness=0.7)
    return root


def extract(folder, out, method="hog"):
    assert main(["extract", "--method", method, "--images", str(folder), "--out", str(out), "--workers", "0"]) == 0
    return out


def evaluate(route, tmp_path, name, *method):
    out = tmp_path / f"{name}.json"
    assert main(["evaluate", "--data", str(route), "--reference", "day", "--query", "dusk", *method,
                 "--json", str(out)]) == 0
    result = json.loads(out.read_text())["results"][0]
    return {k: result[k] for k in ("recall_at_n", "recall_at_100_precision", "auc_pr", "precision_at_max_recall",
                                   "pr_curve", "per_acceptance")}


def test_extracts_vectors_give_the_methods_own_numbers_exactly(route, tmp_path):
    day, dusk = extract(route / "day", tmp_path / "day.npz"), extract(route / "dusk", tmp_path / "dusk.npz")
    own = evaluate(route, tmp_path, "own", "--method", "hog")
    looked_up = evaluate(route, tmp_path, "pre", "--method", "precomputed", "--vectors", str(day), "--vectors",
                         str(dusk))
    assert looked_up == own


def test_the_same_file_name_in_two_folders_is_told_apart_by_its_folder(route, tmp_path):
    day, dusk = extract(route / "day", tmp_path / "day.npz"), extract(route / "dusk", tmp_path / "dusk.npz")
    d = create("precomputed", vectors=[str(day), str(dusk)])
    hog = create("hog")
    from fdnet.descriptors.base import describe_paths

    paths = [route / "dusk" / "frame_003.png", route / "day" / "frame_003.png"]
    np.testing.assert_array_equal(describe_paths(d, paths, workers=0), describe_paths(hog, paths, workers=0))


def test_an_npy_with_its_names_list(route, tmp_path):
    hog = create("hog")
    from fdnet.descriptors.base import describe_paths

    paths = sorted((route / "day").glob("*.png"))
    vectors = describe_paths(hog, paths, workers=0)
    np.save(tmp_path / "v.npy", vectors)
    (tmp_path / "v.txt").write_text("".join(f"day/{p.name}\n" for p in paths))  # the default names list
    d = create("precomputed", vectors=str(tmp_path / "v.npy"))
    np.testing.assert_array_equal(describe_paths(d, paths[::-1], workers=0), vectors[::-1])
    (tmp_path / "v.txt").rename(tmp_path / "names.list")
    with pytest.raises(DataError, match="no names list"):
        create("precomputed", vectors=str(tmp_path / "v.npy"))
    assert create("precomputed", vectors=str(tmp_path / "v.npy"), names=str(tmp_path / "names.list")).dim == 2 * 0 + \
        vectors.shape[1]


def test_equal_candidates_are_an_error_not_a_guess(tmp_path):
    np.save(tmp_path / "v.npy", np.eye(3, 4, dtype=np.float32))
    (tmp_path / "v.txt").write_text("a/day/frame.png\nb/day/frame.png\ndusk/frame.png\n")
    d = create("precomputed", vectors=str(tmp_path / "v.npy"))
    assert d.row_of(tmp_path / "b" / "day" / "frame.png") == 1
    assert d.row_of(tmp_path / "dusk" / "frame.png") == 2
    with pytest.raises(DataError, match="two vectors fit this image equally well"):
        d.row_of(tmp_path / "c" / "day" / "frame.png")
    with pytest.raises(DataError, match="no vector for this image"):  # the folder disagrees: never dusk's
        d.row_of(tmp_path / "night" / "frame.png")


@pytest.mark.parametrize("case, message", [
    ("missing_image", "no vector for this image"),
    ("not_vectors", "not a readable .npz"),
    ("missing_file", "vectors file not found"),
    ("no_vectors", "give the vectors with --vectors"),
    ("wrong_suffix", "not a vectors file fdnet reads"),
])
def test_bad_vectors_are_one_line_errors(case, message, route, tmp_path, capsys):
    day = extract(route / "day", tmp_path / "day.npz")
    vectors = {"missing_image": [str(day)], "not_vectors": [str(tmp_path / "bad.npz")],
               "missing_file": [str(tmp_path / "none.npz")], "no_vectors": [],
               "wrong_suffix": [str(tmp_path / "v.csv")]}[case]
    (tmp_path / "bad.npz").write_text("not a zip")
    (tmp_path / "v.csv").write_text("1,2\n")
    args = ["match", "--reference", str(route / "day"), "--query", str(route / "dusk"), "--method", "precomputed",
            "--out", str(tmp_path / "m.csv")]
    for v in vectors:
        args += ["--vectors", v]
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and message in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    if case == "missing_image":  # names the first image without a vector and the files searched
        assert str(route / "dusk" / "frame_000.png") in err and str(day) in err
    assert not (tmp_path / "m.csv").exists()


def test_vectors_is_refused_for_a_method_that_computes_its_own(route, tmp_path, capsys):
    day = extract(route / "day", tmp_path / "day.npz")
    assert main(["match", "--reference", str(route / "day"), "--query", str(route / "day"), "--method", "hog",
                 "--vectors", str(day), "--out", str(tmp_path / "m.csv")]) == 2
    assert "--vectors is for --method precomputed" in capsys.readouterr().err


def test_loop_closure_and_the_database_take_precomputed_vectors(tmp_path, capsys):
    route = tmp_path / "loop"
    write_random_places(route, 8, seed=5)
    for i in range(8):  # the route again: frame 8 + i revisits frame i
        (route / f"frame_{8 + i:03d}.png").write_bytes((route / f"frame_{i:03d}.png").read_bytes())
    vectors = extract(route, tmp_path / "loop.npz")
    common = ["--images", str(route), "--sequence-length", "1", "--exclude-last", "3", "--accept", "margin",
              "--threshold", "0.01"]
    assert main(["loop-closure", *common, "--method", "hog", "--out", str(tmp_path / "own.csv")]) == 0
    assert main(["loop-closure", *common, "--method", "precomputed", "--vectors", str(vectors), "--out",
                 str(tmp_path / "pre.csv")]) == 0
    own, pre = read_csv_rows(tmp_path / "own.csv"), read_csv_rows(tmp_path / "pre.csv")
    assert len(own) >= 8 and [(r["query"], r["match"]) for r in pre] == [(r["query"], r["match"]) for r in own]

    db = tmp_path / "map.db"
    assert main(["database", "build", "--images", str(route), "--method", "precomputed", "--vectors", str(vectors),
                 "--db", str(db)]) == 0
    other = tmp_path / "other.npz"
    extract(route, other, method="gist")
    capsys.readouterr()
    assert main(["database", "add", "--db", str(db), "--images", str(route), "--method", "precomputed",
                 "--vectors", str(other)]) == 2  # other vectors: another model's, refused
    assert "Traceback" not in capsys.readouterr().err


def test_pixel_arrays_cannot_be_looked_up(route, tmp_path):
    from fdnet.decisions.loop_closure import LoopClosureDetector

    day = extract(route / "day", tmp_path / "day.npz")
    detector = LoopClosureDetector(create("precomputed", vectors=str(day)), exclude_last=3, rule="margin", threshold=0.5)
    assert detector.process(route / "day" / "frame_000.png") is None  # a path: looked up
    with pytest.raises(DataError, match="not pixel arrays"):
        detector.process(np.zeros((24, 32, 3), np.uint8))


def test_reproduce_compares_precomputed_vectors_with_the_method_that_made_them(route, tmp_path):
    day, dusk = extract(route / "day", tmp_path / "day.npz"), extract(route / "dusk", tmp_path / "dusk.npz")
    assert main(["reproduce", "--data", str(route), "--method", "precomputed,hog", "--vectors", str(day),
                 "--vectors", str(dusk), "--experiments", "comparison", "--out", str(tmp_path / "report"),
                 "--cache", str(tmp_path / "cache"), "--no-progress"]) == 0
    comparison = json.loads((tmp_path / "report" / "comparison.json").read_text())
    for pair in comparison["pairs"]:
        by_method = {r["method"]: r for r in pair["results"]}
        for key in ("recall_at_n", "recall_at_100_precision", "auc_pr"):
            assert by_method["precomputed"][key] == by_method["hog"][key], key


def test_hlocs_global_features_are_looked_up_by_their_relative_names(route, tmp_path, capsys):
    pytest.importorskip("h5py", reason="optional extra fdnet[hloc] not installed")
    from fdnet.descriptors.base import describe_paths
    from fdnet.descriptors.hloc_formats import write_global_features

    paths = sorted((route / "day").glob("*.png")) + sorted((route / "dusk").glob("*.png"))
    vectors = describe_paths(create("hog"), paths, workers=0)
    h5 = tmp_path / "global-feats-hog.h5"
    write_global_features(h5, [f"{p.parent.name}/{p.name}" for p in paths], vectors)  # relative to route/
    assert evaluate(route, tmp_path, "h5", "--method", "precomputed", "--vectors", str(h5)) == \
        evaluate(route, tmp_path, "own", "--method", "hog")

    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(h5.read_bytes()[: h5.stat().st_size // 2])
    capsys.readouterr()
    assert main(["match", "--reference", str(route / "day"), "--query", str(route / "dusk"), "--method",
                 "precomputed", "--vectors", str(truncated), "--out", str(tmp_path / "m.csv")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and str(truncated) in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
