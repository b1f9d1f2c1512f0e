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
    assert (
        main(["evaluate", "--data", str(route), "--reference", "day", "--query", "dusk", *method, "--json", str(out)])
        == 0
    )
    result = json.loads(out.read_text())["results"][0]
    return {
        k: result[k]
        for k in (
            "recall_at_n",
            "recall_at_100_precision",
            "auc_pr",
            "precision_at_max_recall",
            "pr_curve",
            "per_acceptance",
        )
    }


def test_extracts_vectors_give_the_methods_own_numbers_exactly(route, tmp_path):
    day, dusk = extract(route / "day", tmp_path / "day.npz"), extract(route / "dusk", tmp_path / "dusk.npz")
    own = evaluate(route, tmp_path, "own", "--method", "hog")
    looked_up = evaluate(
        route, tmp_path, "pre", "--method", "precomputed", "--vectors", str(day), "--vectors", str(dusk)
    )
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
    assert (
        create("precomputed", vectors=str(tmp_path / "v.npy"), names=str(tmp_path / "names.list")).dim
        == 2 * 0 + vectors.shape[1]
    )


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


@pytest.mark.parametrize(
    "case, message",
    [
        ("missing_image", "no vector for this image"),
        ("not_vectors", "not a readable .npz"),
        ("missing_file", "vectors file not found"),
        ("no_vectors", "give the vectors with --vectors"),
        ("wrong_suffix", "not a vectors file fdnet reads"),
    ],
)
def test_bad_vectors_are_one_line_errors(case, message, route, tmp_path, capsys):
    day = extract(route / "day", tmp_path / "day.npz")
    vectors = {
        "missing_image": [str(day)],
        "not_vectors": [str(tmp_path / "bad.npz")],
        "missing_file": [str(tmp_path / "none.npz")],
        "no_vectors": [],
        "wrong_suffix": [str(tmp_path / "v.csv")],
    }[case]
    (tmp_path / "bad.npz").write_text("not a zip")
    (tmp_path / "v.csv").write_text("1,2\n")
    args = [
        "match",
        "--reference",
        str(route / "day"),
        "--query",
        str(route / "dusk"),
        "--method",
        "precomputed",
        "--out",
        str(tmp_path / "m.csv"),
    ]
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
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "day"),
                "--query",
                str(route / "day"),
                "--method",
                "hog",
                "--vectors",
                str(day),
                "--out",
                str(tmp_path / "m.csv"),
            ]
        )
        == 2
    )
    assert "none of the methods hog has a setting vectors (precomputed has)" in capsys.readouterr().err


def test_loop_closure_and_the_database_take_precomputed_vectors(tmp_path, capsys):
    route = tmp_path / "loop"
    write_random_places(route, 8, seed=5)
    for i in range(8):  # the route again: frame 8 + i revisits frame i
        (route / f"frame_{8 + i:03d}.png").write_bytes((route / f"frame_{i:03d}.png").read_bytes())
    vectors = extract(route, tmp_path / "loop.npz")
    common = [
        "--images",
        str(route),
        "--sequence-length",
        "1",
        "--exclude-last",
        "3",
        "--accept",
        "margin",
        "--threshold",
        "0.01",
    ]
    assert main(["loop-closure", *common, "--method", "hog", "--out", str(tmp_path / "own.csv")]) == 0
    assert (
        main(
            [
                "loop-closure",
                *common,
                "--method",
                "precomputed",
                "--vectors",
                str(vectors),
                "--out",
                str(tmp_path / "pre.csv"),
            ]
        )
        == 0
    )
    own, pre = read_csv_rows(tmp_path / "own.csv"), read_csv_rows(tmp_path / "pre.csv")
    assert len(own) >= 8 and [(r["query"], r["match"]) for r in pre] == [(r["query"], r["match"]) for r in own]

    db = tmp_path / "map.db"
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(route),
                "--method",
                "precomputed",
                "--vectors",
                str(vectors),
                "--db",
                str(db),
            ]
        )
        == 0
    )
    other = tmp_path / "other.npz"
    extract(route, other, method="gist")
    capsys.readouterr()
    assert (
        main(
            [
                "database",
                "add",
                "--db",
                str(db),
                "--images",
                str(route),
                "--method",
                "precomputed",
                "--vectors",
                str(other),
            ]
        )
        == 2
    )  # other vectors: another model's, refused
    assert "Traceback" not in capsys.readouterr().err


def test_pixel_arrays_cannot_be_looked_up(route, tmp_path):
    from fdnet.decisions.loop_closure import LoopClosureDetector

    day = extract(route / "day", tmp_path / "day.npz")
    detector = LoopClosureDetector(
        create("precomputed", vectors=str(day)), exclude_last=3, rule="margin", threshold=0.5
    )
    assert detector.process(route / "day" / "frame_000.png") is None  # a path: looked up
    with pytest.raises(DataError, match="not pixel arrays"):
        detector.process(np.zeros((24, 32, 3), np.uint8))


def test_reproduce_compares_precomputed_vectors_with_the_method_that_made_them(route, tmp_path):
    day, dusk = extract(route / "day", tmp_path / "day.npz"), extract(route / "dusk", tmp_path / "dusk.npz")
    assert (
        main(
            [
                "reproduce",
                "--data",
                str(route),
                "--method",
                "precomputed,hog",
                "--vectors",
                str(day),
                "--vectors",
                str(dusk),
                "--experiments",
                "comparison",
                "--out",
                str(tmp_path / "report"),
                "--cache",
                str(tmp_path / "cache"),
                "--no-progress",
            ]
        )
        == 0
    )
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
    assert evaluate(route, tmp_path, "h5", "--method", "precomputed", "--vectors", str(h5)) == evaluate(
        route, tmp_path, "own", "--method", "hog"
    )

    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(h5.read_bytes()[: h5.stat().st_size // 2])
    capsys.readouterr()
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "day"),
                "--query",
                str(route / "dusk"),
                "--method",
                "precomputed",
                "--vectors",
                str(truncated),
                "--out",
                str(tmp_path / "m.csv"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and str(truncated) in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------ one vector, one image
def test_names_without_folders_never_give_one_folders_vector_to_another(route, tmp_path, capsys):
    """hloc's own file of one folder names its images without a folder (names relative to that
    folder, and no record of which): day's file used for day and dusk once gave dusk day's vectors."""
    pytest.importorskip("h5py", reason="optional extra fdnet[hloc] not installed")
    from fdnet.descriptors.base import describe_paths
    from fdnet.descriptors.hloc_formats import write_global_features

    paths = sorted((route / "day").glob("*.png"))
    day = tmp_path / "day.h5"
    write_global_features(day, [p.name for p in paths], describe_paths(create("hog"), paths, workers=0))
    capsys.readouterr()
    out = tmp_path / "m.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "day"),
                "--query",
                str(route / "dusk"),
                "--method",
                "precomputed",
                "--vectors",
                str(day),
                "--out",
                str(out),
                "--workers",
                "0",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "one vector cannot be two images'" in err and str(route / "dusk" / "frame_000.png") in err
    assert "warning: " in err and "without a folder" in err  # said when the file is loaded
    assert [line for line in err.splitlines() if "error" in line][0].startswith("fdnet match: error: ")
    assert "Traceback" not in err and not out.exists()
    # the folder it was made from: its own vectors, with the warning
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "day"),
                "--query",
                str(route / "day"),
                "--method",
                "precomputed",
                "--vectors",
                str(day),
                "--out",
                str(out),
                "--workers",
                "0",
            ]
        )
        == 0
    )


def test_a_folder_name_shared_by_two_routes_is_not_one_routes_vectors_for_both(tmp_path, capsys):
    first, second = tmp_path / "first" / "day", tmp_path / "second" / "day"
    write_random_places(first, 4, seed=1)
    write_random_places(second, 4, seed=2)
    np.save(tmp_path / "v.npy", np.random.default_rng(0).random((4, 8)).astype(np.float32))
    (tmp_path / "v.txt").write_text("".join(f"day/frame_{i:03d}.png\n" for i in range(4)))  # relative to first/
    d = create("precomputed", vectors=str(tmp_path / "v.npy"))
    d.lookup([first / "frame_000.png", first / "frame_000.png"])  # the same image twice: fine
    with pytest.raises(DataError, match="already took"):
        d.lookup([second / "frame_000.png"])


def test_a_name_at_two_depths_resolves_to_the_one_whose_folders_agree(tmp_path):
    """hloc's names of a tree (--recursive) may hold day/0001.png and x/day/0001.png: the first is
    ROOT/day/0001.png's, not an equal candidate."""
    np.save(tmp_path / "v.npy", np.eye(2, 4, dtype=np.float32))
    (tmp_path / "v.txt").write_text("day/0001.png\nx/day/0001.png\n")
    d = create("precomputed", vectors=str(tmp_path / "v.npy"))
    assert d.row_of(tmp_path / "root" / "day" / "0001.png") == 0
    assert d.row_of(tmp_path / "root" / "x" / "day" / "0001.png") == 1


def test_a_symlinked_image_folder_finds_the_vectors_of_its_target(route, tmp_path):
    day, dusk = extract(route / "day", tmp_path / "day.npz"), extract(route / "dusk", tmp_path / "dusk.npz")
    (tmp_path / "linked").symlink_to(route / "day", target_is_directory=True)
    out = tmp_path / "m.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(tmp_path / "linked"),
                "--query",
                str(route / "dusk"),
                "--method",
                "precomputed",
                "--vectors",
                str(day),
                "--vectors",
                str(dusk),
                "--out",
                str(out),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    own = tmp_path / "own.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(tmp_path / "linked"),
                "--query",
                str(route / "dusk"),
                "--method",
                "hog",
                "--out",
                str(own),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    assert read_csv_rows(out) == read_csv_rows(own)


def test_images_whose_names_differ_only_by_case_are_two_images(tmp_path):
    np.save(tmp_path / "v.npy", np.eye(2, 4, dtype=np.float32))
    (tmp_path / "v.txt").write_text("day/A.png\nday/a.png\n")
    d = create("precomputed", vectors=str(tmp_path / "v.npy"))
    assert d.row_of(tmp_path / "day" / "A.png") == 0 and d.row_of(tmp_path / "day" / "a.png") == 1
    with pytest.raises(DataError, match="no vector for this image"):
        d.row_of(tmp_path / "Day" / "a.png")


# ------------------------------------------------------------------ what a vectors file may hold
VECTORS = np.random.default_rng(0).random((3, 4)).astype(np.float32)
NAMES = np.array([f"day/frame_{i:03d}.png" for i in range(3)])


def _write_npz(path, **arrays):
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize(
    "case, message",
    [
        ("object_vectors", "holds Python objects (dtype object), which are never unpickled"),
        ("object_names", "holds Python objects (dtype object), which are never unpickled"),
        ("no_names", "no names array"),
        ("one_dimensional", "vectors of shape (4,)"),
        ("nan_row", "the vector of day/frame_001.png holds NaN"),
        ("integer_names", "names is an array of int64"),
        ("names_2d", "expected one text per image"),
        ("complex", "holds complex64, not real numbers"),
        ("empty_name", "row 0 has an empty image name"),
        ("sources_short", "2 sources for 3 names"),
        ("directory", "not a file"),
        ("beyond_float32", "beyond float32's range"),
        ("zero_row", "the vector of day/frame_001.png is all zero"),
    ],
)
def test_a_vectors_file_holding_the_wrong_things_is_one_error_naming_it(case, message, tmp_path):
    path = tmp_path / f"{case}.npz"
    if case == "object_vectors":
        _write_npz(path, descriptors=np.array(list(VECTORS), dtype=object), names=NAMES)
    elif case == "object_names":
        _write_npz(path, descriptors=VECTORS, names=np.array(list(NAMES), dtype=object))
    elif case == "no_names":
        _write_npz(path, descriptors=VECTORS)
    elif case == "one_dimensional":
        _write_npz(path, descriptors=VECTORS[0], names=NAMES[:1])
    elif case == "nan_row":
        _write_npz(path, descriptors=np.where(np.arange(3)[:, None] == 1, np.nan, VECTORS), names=NAMES)
    elif case == "integer_names":
        _write_npz(path, descriptors=VECTORS, names=np.arange(3))
    elif case == "names_2d":
        _write_npz(path, descriptors=VECTORS, names=NAMES.reshape(3, 1))
    elif case == "complex":
        _write_npz(path, descriptors=VECTORS.astype(np.complex64), names=NAMES)
    elif case == "empty_name":
        _write_npz(path, descriptors=VECTORS, names=np.array(["", "a.png", "b.png"]))
    elif case == "sources_short":
        _write_npz(path, descriptors=VECTORS, names=NAMES, sources=np.array(["/x", "/y"]))
    elif case == "directory":
        path.mkdir()
    elif case == "beyond_float32":
        _write_npz(path, descriptors=np.full((3, 4), 1e300), names=NAMES)
    elif case == "zero_row":
        _write_npz(path, descriptors=np.where(np.arange(3)[:, None] == 1, 0.0, VECTORS), names=NAMES)
    with pytest.raises(DataError) as caught:
        create("precomputed", vectors=str(path))
    text = str(caught.value)
    assert text.startswith(str(path)) and message in text and "\n" not in text, text


def test_names_kept_as_bytes_and_huge_numbers_are_read_as_meant(tmp_path):
    path = _write_npz(tmp_path / "v.npz", descriptors=VECTORS * 1e30, names=np.array([n.encode() for n in NAMES]))
    d = create("precomputed", vectors=str(path))
    assert d.row_of(tmp_path / "day" / "frame_002.png") == 2  # not "b'day/frame_002.png'"
    np.testing.assert_allclose(np.linalg.norm(d.vectors, axis=1), 1.0, rtol=1e-6)  # not zeros from an overflow
    np.testing.assert_allclose(d.vectors, VECTORS / np.linalg.norm(VECTORS, axis=1, keepdims=True), rtol=1e-5)


def test_a_names_list_of_the_wrong_length_or_with_blank_lines(tmp_path):
    np.save(tmp_path / "v.npy", VECTORS)
    (tmp_path / "v.txt").write_text("a.png\nb.png\n")
    with pytest.raises(DataError, match="3 vectors but 2 image names"):
        create("precomputed", vectors=str(tmp_path / "v.npy"))
    (tmp_path / "v.txt").write_text("day/a.png\n\nday/b.png\r\nday/c.png\n\n")  # blank lines are no rows
    assert create("precomputed", vectors=str(tmp_path / "v.npy")).row_of(tmp_path / "day" / "c.png") == 2


def test_the_same_file_given_twice_is_said_so(route, tmp_path, capsys):
    day = extract(route / "day", tmp_path / "day.npz")
    (tmp_path / "again.npz").symlink_to(day)
    for second in (str(tmp_path / "." / "day.npz"), str(tmp_path / "again.npz")):
        with pytest.raises(DataError, match="given twice"):
            create("precomputed", vectors=[str(day), second])


def test_fdnets_own_h5_records_its_method_so_another_methods_vectors_are_refused(route, tmp_path):
    pytest.importorskip("h5py", reason="optional extra fdnet[hloc] not installed")
    raw, sad = tmp_path / "day_raw.npz", tmp_path / "dusk_sad.h5"
    extract(route / "day", raw, method="raw")
    extract(route / "dusk", sad, method="sad")  # the same length (2048), another method
    with pytest.raises(DataError, match="vectors of raw, but .*dusk_sad.h5's are of sad"):
        create("precomputed", vectors=[str(sad), str(raw)])
    assert create("precomputed", vectors=str(sad)).settings()["source_method"] == "sad"


def test_fdnets_own_h5_keeps_its_folder_so_one_folders_vectors_never_serve_another(route, tmp_path, capsys):
    pytest.importorskip("h5py", reason="optional extra fdnet[hloc] not installed")
    day = tmp_path / "day.h5"
    assert (
        main(
            [
                "extract",
                "--method",
                "hog",
                "--format",
                "h5",
                "--images",
                str(route / "day"),
                "--out",
                str(day),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "day"),
                "--query",
                str(route / "dusk"),
                "--method",
                "precomputed",
                "--vectors",
                str(day),
                "--out",
                str(tmp_path / "m.csv"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "no vector for this image" in err and "dusk" in err and not (tmp_path / "m.csv").exists()
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "day"),
                "--query",
                str(route / "day"),
                "--method",
                "precomputed",
                "--vectors",
                str(day),
                "--out",
                str(tmp_path / "m.csv"),
            ]
        )
        == 0
    )


def test_extract_never_writes_over_the_vectors_it_reads(route, tmp_path, capsys):
    vectors = extract(route / "day", tmp_path / "day.npz")
    before = vectors.read_bytes()
    capsys.readouterr()
    assert (
        main(
            [
                "extract",
                "--method",
                "precomputed",
                "--vectors",
                str(vectors),
                "--images",
                str(route / "day"),
                "--out",
                str(vectors),
            ]
        )
        == 2
    )
    assert "is the --vectors file the command reads" in capsys.readouterr().err
    assert vectors.read_bytes() == before


@pytest.mark.parametrize("suffix", ["npz", "h5"])
def test_vectors_of_another_route_with_the_same_layout_are_refused_naming_the_image(suffix, tmp_path, capsys):
    """Route r's vectors (file name and parent folder match) must not serve route r2: fdnet's own
    files (.npz and .h5) record each image's size and modification time, and the image is checked
    against them."""
    if suffix == "h5":
        pytest.importorskip("h5py", reason="optional extra fdnet[hloc] not installed")
    r, r2 = tmp_path / "r", tmp_path / "r2"
    write_random_places(r / "summer", 4, seed=1)
    write_random_places(r2 / "summer", 4, seed=2, brightness=0.5)
    vectors = extract(r / "summer", tmp_path / f"r.{suffix}")
    if suffix == "npz":
        with np.load(vectors) as data:
            sizes = [(r / "summer" / f"frame_{i:03d}.png").stat().st_size for i in range(4)]
            assert data["sizes"].tolist() == sizes
    d = create("precomputed", vectors=str(vectors))
    d.lookup([r / "summer" / "frame_000.png"])  # its own image: fine
    with pytest.raises(
        DataError,
        match=rf"r2/summer/frame_000\.png: not the image that .*r\.{suffix}'s vector for "
        r".*/r/summer/frame_000\.png was computed from \(\d+ bytes here",
    ):
        create("precomputed", vectors=str(vectors)).lookup([r2 / "summer" / "frame_000.png"])
    code = main(
        [
            "extract",
            "--method",
            "precomputed",
            "--vectors",
            str(vectors),
            "--images",
            str(r2 / "summer"),
            "--out",
            str(tmp_path / f"again.{suffix}"),
            "--workers",
            "0",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "r2/summer/frame_000.png: not the image" in err and len(err.strip().splitlines()) == 1


def test_a_compressed_npz_claiming_more_memory_than_allowed_is_refused_before_it_is_read(tmp_path, monkeypatch):
    from fdnet.data import arrays

    path = tmp_path / "bomb.npz"
    np.savez_compressed(path, descriptors=np.ones((2000, 400), np.float32), names=np.array(["a.png"] * 2000))
    monkeypatch.setattr(arrays, "physical_memory_bytes", lambda: 1 << 20)  # this process may use 1 MiB

    def never(*args, **kwargs):
        raise AssertionError("the array was read")

    monkeypatch.setattr(np.lib.format, "read_array", never)
    with pytest.raises(
        DataError, match=r"bomb\.npz \(array 'descriptors'\): shape \(2000, 400\) float32 needs 3\.1 MiB"
    ):
        create("precomputed", vectors=str(path))


def test_a_precomputed_database_grows_with_later_vectors_of_the_same_model(tmp_path, capsys):
    """fdnet extract's files record the model that made them: a database built from one folder's
    vectors takes another folder's of the same model; vectors that record no model are identified
    by their bytes, and the refusal says so."""
    first, second = write_random_places(tmp_path / "a", 4, seed=1), write_random_places(tmp_path / "b", 3, seed=2)
    db = tmp_path / "map.db"
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(first),
                "--method",
                "precomputed",
                "--vectors",
                str(extract(first, tmp_path / "a.npz")),
                "--db",
                str(db),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "database",
                "add",
                "--db",
                str(db),
                "--images",
                str(second),
                "--method",
                "precomputed",
                "--vectors",
                str(extract(second, tmp_path / "b.npz")),
            ]
        )
        == 0
    )
    from fdnet.matching.database import PlaceDatabase

    with PlaceDatabase.open(db) as opened:
        assert len(opened) == 7
    with np.load(tmp_path / "b.npz") as data:
        np.save(tmp_path / "b.npy", data["descriptors"])
    (tmp_path / "b.txt").write_text("".join(f"b/frame_{i:03d}.png\n" for i in range(3)))
    capsys.readouterr()
    assert (
        main(
            [
                "database",
                "add",
                "--db",
                str(db),
                "--images",
                str(second),
                "--method",
                "precomputed",
                "--vectors",
                str(tmp_path / "b.npy"),
            ]
        )
        == 2
    )
    assert "a precomputed database grows only with vectors files that record the model" in capsys.readouterr().err
