"""`fdnet match` and `fdnet database` on images the test makes."""

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from fdnet.cli import main

from conftest import read_csv_rows, write_random_places


def make_route(folder, n=12, seed=0, brightness=1.0):
    """n distinct random-texture places; the same seed gives the same places."""
    return write_random_places(folder, n, seed, brightness)


@pytest.mark.parametrize("index", ["exact", "flat", "hnsw"])
def test_match_writes_ranked_candidates(tmp_path, index):
    ref = make_route(tmp_path / "ref")
    qry = make_route(tmp_path / "qry", brightness=0.7)  # same places, darker
    out = tmp_path / "matches.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(qry),
                "--method",
                "raw",
                "--top-k",
                "3",
                "--index",
                index,
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = read_csv_rows(out)
    assert len(rows) == 12 * 3
    best = [r for r in rows if r["rank"] == "1"]
    assert all(Path(r["query"]).name == Path(r["reference"]).name for r in best)
    scores = [float(r["score"]) for r in rows if r["query"].endswith("/frame_000.png")]
    assert scores == sorted(scores, reverse=True)


def test_match_with_sequences_and_non_dot_product_method(tmp_path, capsys):
    ref = make_route(tmp_path / "ref")
    qry = make_route(tmp_path / "qry", brightness=0.8)
    out = tmp_path / "seq.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(qry),
                "--method",
                "sad",
                "--sequence-length",
                "3",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    best = [r for r in read_csv_rows(out) if r["rank"] == "1"]
    assert all(Path(r["query"]).name == Path(r["reference"]).name for r in best)
    # SAD is not a dot product: a faiss index would rank by the wrong measure.
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(qry),
                "--method",
                "sad",
                "--index",
                "flat",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    assert "dot product" in capsys.readouterr().err


def test_match_bad_input_is_a_clear_error(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    ref = make_route(tmp_path / "ref")
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(empty),
                "--method",
                "raw",
                "--out",
                str(tmp_path / "x.csv"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert str(empty) in err and "no images" in err
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(ref),
                "--method",
                "nope",
                "--out",
                str(tmp_path / "x.csv"),
            ]
        )
        == 2
    )
    assert "unknown method" in capsys.readouterr().err


def test_database_build_add_query(tmp_path):
    first = make_route(tmp_path / "first", n=8, seed=1)
    second = make_route(tmp_path / "second", n=5, seed=2)
    db = tmp_path / "db"
    assert main(["database", "build", "--images", str(first), "--method", "raw", "--db", str(db)]) == 0
    assert main(["database", "add", "--db", str(db), "--images", str(second)]) == 0
    out = tmp_path / "q.csv"
    assert main(["database", "query", "--db", str(db), "--images", str(second), "--top-k", "2", "--out", str(out)]) == 0
    best = [r for r in read_csv_rows(out) if r["rank"] == "1"]
    assert [r["place"] == r["query"] and "second" in r["place"] for r in best] == [True] * 5
    # Excluding the 5 most recent places forces matches into the first batch.
    assert (
        main(["database", "query", "--db", str(db), "--images", str(second), "--exclude-last", "5", "--out", str(out)])
        == 0
    )
    assert all("first" in r["place"] for r in read_csv_rows(out))


def test_method_options_go_to_the_methods_that_declare_them(tmp_path, capsys):
    """One rule for every method option flag: METHOD:VALUE goes to that method, a bare value to
    every method of the command whose settings declare it, refused when none does."""
    import argparse

    from fdnet.cli.common import method_options
    from fdnet.errors import ConfigError

    args = argparse.Namespace(
        method="fdnet,sad,dbow",
        checkpoint=["runs/a"],
        weights=[],
        vocabulary=["dbow:voc.npz"],
        method_set=["dbow:branching=4", "patch_size=4", "bf16=true"],
    )
    assert method_options(args, "fdnet") == {"checkpoint": "runs/a", "bf16": True}
    assert method_options(args, "sad") == {"patch_size": 4}
    assert method_options(args, "dbow") == {"vocabulary": "voc.npz", "branching": 4, "patch_size": 4}
    # a scoped value wins over a bare one, whatever their order
    args.method_set = ["sad:patch_size=2", "patch_size=4"]
    assert method_options(args, "sad") == {"patch_size": 2} and method_options(args, "dbow")["patch_size"] == 4
    refusals = {
        "dim=3": "--method-set dim=3: none of the methods fdnet, sad, dbow has a setting dim "
        "(trunk-whitened, conv3, hybridnet have)",
        "sad:dim=3": "--method-set sad:dim=3: method 'sad' has no setting dim; its settings: size, patch_size",
        "hog:grey=true": "--method-set hog:grey=true: hog is not one of the methods of --method (fdnet, sad, " "dbow)",
    }
    for method_set, message in refusals.items():
        args.method_set = [method_set]
        with pytest.raises(ConfigError) as refused:
            method_options(args, "sad")
        assert str(refused.value) == message
    ref = make_route(tmp_path / "ref", n=3)
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(ref),
                "--method",
                "sad",
                "--checkpoint",
                "runs/x",
                "--out",
                str(tmp_path / "x.csv"),
            ]
        )
        == 2
    )
    assert "--checkpoint runs/x: none of the methods sad has a setting checkpoint" in capsys.readouterr().err


def test_match_lists_unpadded_names_in_natural_order_with_indices_and_names(tmp_path):
    """Rows carry query and reference indices (positions in natural order: frame_2 before
    frame_10) beside the file names."""
    rng = np.random.default_rng(4)
    names = [f"frame_{k}.png" for k in range(1, 13)]
    for folder in ("ref", "qry"):
        (tmp_path / folder).mkdir()
    for name in names:
        img = rng.integers(0, 256, size=(24, 32, 3)).astype(np.uint8)
        Image.fromarray(img).save(tmp_path / "ref" / name)
        Image.fromarray((img * 0.7).astype(np.uint8)).save(tmp_path / "qry" / name)
    out = tmp_path / "matches.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(tmp_path / "ref"),
                "--query",
                str(tmp_path / "qry"),
                "--method",
                "raw",
                "--top-k",
                "2",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = read_csv_rows(out)
    assert list(rows[0]) == ["query_index", "query", "rank", "reference_index", "reference", "score"]
    best = [r for r in rows if r["rank"] == "1"]
    assert [(r["query_index"], r["query"]) for r in best] == [
        (str(i), str(tmp_path / "qry" / n)) for i, n in enumerate(names)
    ]
    assert all(
        r["reference_index"] == r["query_index"] and Path(r["reference"]).name == Path(r["query"]).name for r in best
    )


def test_match_unwritable_out_fails_before_describing_images(tmp_path, capsys, monkeypatch):
    import fdnet.cli.common as common

    def no_work(*args, **kwargs):
        raise AssertionError("a descriptor was made before the output path was checked")

    monkeypatch.setattr(common, "create_descriptor", no_work)
    ref = make_route(tmp_path / "ref", n=3)
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    out = blocker / "matches.csv"  # its parent is a regular file
    assert main(["match", "--reference", str(ref), "--query", str(ref), "--method", "raw", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and str(out) in err and "cannot create the matches CSV" in err


def test_match_keeps_and_reuses_a_saved_index(tmp_path, capsys):
    ref = make_route(tmp_path / "ref", n=50)
    qry = make_route(tmp_path / "qry", n=50, brightness=0.7)
    saved = tmp_path / "map.index"
    outs = []
    for run, extra in enumerate([[], [], ["--index-set", "ivf_lists=2"]]):
        out = tmp_path / f"m{run}.csv"
        assert (
            main(
                [
                    "match",
                    "--reference",
                    str(ref),
                    "--query",
                    str(qry),
                    "--method",
                    "raw",
                    "--index",
                    "ivf",
                    "--index-file",
                    str(saved),
                    "--top-k",
                    "2",
                    "--workers",
                    "0",
                    "--out",
                    str(out),
                    *extra,
                ]
            )
            == 0
        )
        outs.append(read_csv_rows(out))
        printed = capsys.readouterr().out
        assert ("built the ivf index" in printed) == (run != 1)
        assert ("loaded the ivf index" in printed) == (run == 1)
    assert outs[0] == outs[1]
    assert all(Path(r["query"]).name == Path(r["reference"]).name for r in outs[1] if r["rank"] == "1")
    # the index of another map is not reused
    other = make_route(tmp_path / "other", n=40, seed=3)
    assert (
        main(
            [
                "match",
                "--reference",
                str(other),
                "--query",
                str(qry),
                "--method",
                "raw",
                "--index",
                "ivf",
                "--index-file",
                str(saved),
                "--out",
                str(tmp_path / "o.csv"),
            ]
        )
        == 0
    )
    assert "other reference images" in capsys.readouterr().out
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(qry),
                "--method",
                "raw",
                "--index-file",
                str(saved),
                "--out",
                str(tmp_path / "x.csv"),
            ]
        )
        == 2
    )
    assert "--index-file apply to the faiss indexes" in capsys.readouterr().err


@pytest.mark.parametrize("setting, missing", [("radius_m=5", "positions"), ("radius_s=2", "timestamps")])
def test_a_neighbourhood_image_folders_cannot_give_is_refused_before_describing(
    tmp_path, capsys, monkeypatch, setting, missing
):
    from fdnet.descriptors.classic import RawThumbnail

    def describe(self, images):
        raise AssertionError("images were described before the rule was checked")

    monkeypatch.setattr(RawThumbnail, "describe", describe)
    ref = make_route(tmp_path / "ref", n=3)
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(ref),
                "--method",
                "raw",
                "--accept",
                "margin",
                "--accept-set",
                setting,
                "--out",
                str(tmp_path / "m.csv"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and f"has no {missing} of the references" in err


def test_names_a_spreadsheet_would_run_as_formulas_are_written_as_paths(tmp_path):
    """OWASP CSV injection: no cell starts with = + - @ (names are absolute paths; scores are numbers)."""
    ref = make_route(tmp_path / "ref", n=4)
    qry = make_route(tmp_path / "qry", n=4)
    for folder in (ref, qry):
        for old, new in (
            ("frame_000.png", "=HYPERLINK(1).png"),
            ("frame_001.png", "+1.png"),
            ("frame_002.png", "-2.png"),
            ("frame_003.png", "@SUM(A1).png"),
        ):
            (folder / old).rename(folder / new)
    out = tmp_path / "matches.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(qry),
                "--method",
                "raw",
                "--top-k",
                "4",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = read_csv_rows(out)
    names = {r["query"] for r in rows} | {r["reference"] for r in rows}
    # named by absolute path: a cell that starts with / is nothing a spreadsheet runs
    assert {Path(n).name for n in names} == {"=HYPERLINK(1).png", "+1.png", "-2.png", "@SUM(A1).png"}
    assert all(n.startswith("/") for n in names)
    assert not any(r["score"].startswith("'") for r in rows)  # numbers stay numbers, negative ones too


def test_a_name_that_is_not_utf8_is_written_as_its_own_bytes(tmp_path):
    import os

    ref = make_route(tmp_path / "ref", n=3)
    qry = make_route(tmp_path / "qry", n=3)
    os.rename(qry / "frame_001.png", os.path.join(os.fsencode(qry), b"caf\xe9.png"))
    out = tmp_path / "matches.csv"
    assert main(["match", "--reference", str(ref), "--query", str(qry), "--method", "raw", "--out", str(out)]) == 0
    assert b"/caf\xe9.png," in out.read_bytes()


def test_a_negative_sequence_length_is_refused(tmp_path, capsys):
    ref = make_route(tmp_path / "ref", n=3)
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(ref),
                "--method",
                "raw",
                "--out",
                str(tmp_path / "m.csv"),
                "--sequence-length",
                "-2",
            ]
        )
        == 2
    )
    assert (
        "fdnet match: error: --sequence-length must be a whole number of frames, at least 1" in capsys.readouterr().err
    )
    assert not (tmp_path / "m.csv").exists()


def test_a_name_that_is_not_utf8_with_a_saved_index(tmp_path):
    import os

    ref = make_route(tmp_path / "ref", n=3)
    os.rename(ref / "frame_001.png", os.path.join(os.fsencode(ref), b"caf\xe9.png"))
    argv = [
        "match",
        "--reference",
        str(ref),
        "--query",
        str(ref),
        "--method",
        "raw",
        "--index",
        "flat",
        "--index-file",
        str(tmp_path / "index.faiss"),
        "--out",
        str(tmp_path / "m.csv"),
    ]
    assert main(argv) == 0 and main(argv) == 0  # built and saved, then loaded for the same names
    assert b"caf\xe9.png" in (tmp_path / "m.csv").read_bytes()


def test_an_index_file_is_not_reused_for_another_folder_with_the_same_names(tmp_path, capsys):
    """Conditions of one route share file names (summer/images-00010.png, winter/images-00010.png):
    an index built for summer must not answer for winter."""
    from conftest import write_random_places

    summer = write_random_places(tmp_path / "route" / "summer", 6, seed=1)
    winter = write_random_places(tmp_path / "route" / "winter", 6, seed=2)
    saved = tmp_path / "map.idx"
    common = [
        "match",
        "--method",
        "raw",
        "--index",
        "flat",
        "--index-file",
        str(saved),
        "--top-k",
        "1",
        "--workers",
        "0",
        "--query",
        str(summer),
    ]
    assert main([*common, "--reference", str(summer), "--out", str(tmp_path / "a.csv")]) == 0
    capsys.readouterr()
    assert main([*common, "--reference", str(winter), "--out", str(tmp_path / "b.csv")]) == 0
    printed = capsys.readouterr()
    assert "other reference images" in printed.out + printed.err and "loaded the flat index" not in printed.out
    assert main([*common, "--reference", str(winter), "--out", str(tmp_path / "c.csv")]) == 0
    assert "loaded the flat index" in capsys.readouterr().out


def _pairs_route(tmp_path, n=8):
    """``route/{map,now}``: n places, the query copies darker (the names hloc's image_dir sees)."""
    route = tmp_path / "route"
    return make_route(route / "map", n), make_route(route / "now", n, brightness=0.7)


def _relative(name, root):
    return Path(name).relative_to(root).as_posix()


def test_match_pairs_out_gives_each_querys_top_k_of_the_csv(tmp_path, capsys):
    from fdnet.descriptors.hloc_formats import read_pairs

    ref, qry = _pairs_route(tmp_path)
    out, pairs = tmp_path / "matches.csv", tmp_path / "pairs.txt"
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(qry),
                "--method",
                "raw",
                "--top-k",
                "3",
                "--workers",
                "0",
                "--out",
                str(out),
                "--pairs-out",
                str(pairs),
            ]
        )
        == 0
    )
    root = tmp_path / "route"  # the folder holding --reference and --query: hloc's image_dir
    assert (
        f"wrote {pairs}: 24 pairs (top-3 per query) for hloc, the images named relative to {root}"
        in capsys.readouterr().out
    )
    expected = [(_relative(r["query"], root), _relative(r["reference"], root)) for r in read_csv_rows(out)]
    assert read_pairs(pairs) == expected and len(expected) == 8 * 3
    assert expected[0] == ("now/frame_000.png", "map/frame_000.png")
    assert all((root / q).is_file() and (root / r).is_file() for q, r in read_pairs(pairs))


def test_match_pairs_out_alone_and_accepted_only(tmp_path, capsys):
    from fdnet.descriptors.hloc_formats import read_pairs

    ref, qry = _pairs_route(tmp_path)
    pairs = tmp_path / "pairs.txt"
    common = [
        "match",
        "--reference",
        str(ref),
        "--query",
        str(qry),
        "--method",
        "raw",
        "--workers",
        "0",
        "--pairs-out",
        str(pairs),
    ]
    # no --out: the pairs file alone; --accept without a threshold: every query's accepted match
    assert main([*common, "--accept", "margin", "--pairs-accepted-only"]) == 0
    assert read_pairs(pairs) == [(f"now/frame_{i:03d}.png", f"map/frame_{i:03d}.png") for i in range(8)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pairs.txt", "route"]
    # a gate that rejects every match: every query a new place, no pair
    assert main([*common, "--accept", "margin+floor", "--accept-set", "floor:min=2", "--pairs-accepted-only"]) == 0
    assert read_pairs(pairs) == [] and "0 accepted pairs" in capsys.readouterr().out
    assert main([*common, "--pairs-accepted-only"]) == 2  # no decision to accept by
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: --pairs-accepted-only needs a decision") and err.count("\n") == 1
    assert main(common[:-2]) == 2
    assert "give --out matches.csv, --pairs-out pairs.txt, or both" in capsys.readouterr().err


def test_match_pairs_accepted_only_with_a_calibration_are_the_accepted_rows(tmp_path, capsys):
    from fdnet.descriptors.hloc_formats import read_pairs

    rng = np.random.default_rng(1)
    root = tmp_path / "route"
    for condition in ("map", "now"):
        (root / condition).mkdir(parents=True)
    for i in range(16):  # places 3, 7 and 11 seen now show other textures: wrong best matches
        place = rng.integers(0, 256, size=(24, 32, 3))
        now = (
            rng.integers(0, 256, size=place.shape)
            if i in (3, 7, 11)
            else np.clip(place * 0.25 + rng.normal(0, 90, place.shape), 0, 255)
        )
        Image.fromarray(place.astype(np.uint8)).save(root / "map" / f"{i:03d}.png")
        Image.fromarray(now.astype(np.uint8)).save(root / "now" / f"{i:03d}.png")
    cal = tmp_path / "cal.yaml"
    assert (
        main(
            [
                "calibrate",
                "--data",
                str(root),
                "--reference",
                "map",
                "--query",
                "now",
                "--method",
                "raw",
                "--workers",
                "0",
                "--accept",
                "margin",
                "--target-precision",
                "1",
                "--out",
                str(cal),
            ]
        )
        == 0
    )
    out, pairs = tmp_path / "m.csv", tmp_path / "pairs.txt"
    assert (
        main(
            [
                "match",
                "--reference",
                str(root / "map"),
                "--query",
                str(root / "now"),
                "--method",
                "raw",
                "--calibration",
                str(cal),
                "--workers",
                "0",
                "--out",
                str(out),
                "--pairs-out",
                str(pairs),
                "--pairs-accepted-only",
            ]
        )
        == 0
    )
    accepted = [
        (_relative(r["query"], root), _relative(r["reference"], root))
        for r in read_csv_rows(out)
        if r["accepted"] == "1"
    ]
    assert read_pairs(pairs) == accepted and 0 < len(accepted) < 16
    assert f"{len(accepted)} accepted pairs" in capsys.readouterr().out


def test_match_pairs_never_pair_a_query_with_itself(tmp_path):
    from fdnet.descriptors.hloc_formats import read_pairs

    ref = make_route(tmp_path / "db", 6)
    pairs = tmp_path / "pairs.txt"
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(ref),
                "--method",
                "raw",
                "--top-k",
                "2",
                "--workers",
                "0",
                "--pairs-out",
                str(pairs),
            ]
        )
        == 0
    )
    found = read_pairs(pairs)
    # names relative to the one folder; each query's 2 best other images, as hloc's pairs_from_retrieval
    assert len(found) == 12 and all(q != r for q, r in found)
    assert [q for q, _ in found] == [f"frame_{i:03d}.png" for i in range(6) for _ in range(2)]


def test_match_refuses_a_name_the_pairs_file_cannot_hold_before_describing(tmp_path, capsys, monkeypatch):
    import fdnet.matching.search as search

    ref, qry = _pairs_route(tmp_path, n=3)
    (ref / "frame_001.png").rename(ref / "frame 001.png")
    monkeypatch.setattr(search, "rank_references", lambda *a, **k: pytest.fail("described the images"))
    out, pairs = tmp_path / "m.csv", tmp_path / "pairs.txt"
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(qry),
                "--method",
                "raw",
                "--workers",
                "0",
                "--out",
                str(out),
                "--pairs-out",
                str(pairs),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith(f"fdnet match: error: {pairs}: image name 'map/frame 001.png' holds whitespace")
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists() and not pairs.exists()


def test_match_on_a_full_disk_writes_both_outputs_or_neither(small_disk, tmp_path, capsys):
    """Room for one output: the CSV was once renamed into place, then the pairs file failed and
    the command said it had written nothing."""
    ref, qry = _pairs_route(tmp_path, n=4)
    out, pairs = small_disk.path / "m.csv", small_disk.path / "pairs.txt"
    small_disk.fill(4096)  # one page: each file alone fits, not both
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(qry),
                "--method",
                "raw",
                "--top-k",
                "3",
                "--workers",
                "0",
                "--out",
                str(out),
                "--pairs-out",
                str(pairs),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and "no space left" in err and err.count("\n") == 1
    assert small_disk.files() == []


def test_match_pairs_out_to_a_read_only_folder_is_refused_before_any_work(
    make_read_only, tmp_path, capsys, monkeypatch
):
    import fdnet.matching.search as search

    ref, qry = _pairs_route(tmp_path, n=3)
    folder = tmp_path / "read-only"
    folder.mkdir()
    make_read_only(folder)
    monkeypatch.setattr(search, "rank_references", lambda *a, **k: pytest.fail("described the images"))
    out = tmp_path / "m.csv"
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(qry),
                "--method",
                "raw",
                "--workers",
                "0",
                "--out",
                str(out),
                "--pairs-out",
                str(folder / "pairs.txt"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith(f"fdnet match: error: {folder / 'pairs.txt'}: ") and "Read-only" in err
    assert err.count("\n") == 1 and not out.exists()


@pytest.mark.parametrize(
    "outputs, message",
    [
        (
            ["--pairs-out", "{tmp}/p.txt", "--index-file", "{tmp}/./p.txt", "--index", "flat"],
            "--pairs-out and --index-file are the same file",
        ),
        (
            ["--out", "{tmp}/m.csv", "--index-file", "{tmp}/m.csv", "--index", "flat"],
            "--out and --index-file are the same file",
        ),
        (["--pairs-out", "{tmp}/link.npz"], "--pairs-out {tmp}/link.npz is the --vectors file"),
        (["--out", "{tmp}/day.npz"], "--out {tmp}/day.npz is the --vectors file"),
        (
            ["--out", "{tmp}/m.csv", "--index-file", "{tmp}/day.npz", "--index", "flat"],
            "--index-file {tmp}/day.npz is the --vectors file",
        ),
    ],
)
def test_match_never_writes_one_output_over_another_or_over_its_input(outputs, message, tmp_path, capsys, monkeypatch):
    import fdnet.matching.search as search

    ref, qry = _pairs_route(tmp_path, n=3)
    vectors = tmp_path / "day.npz"
    assert (
        main(
            [
                "extract",
                "--method",
                "raw",
                "--images",
                str(tmp_path / "route"),
                "--recursive",
                "--out",
                str(vectors),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    (tmp_path / "link.npz").symlink_to(vectors)
    before = vectors.read_bytes()
    capsys.readouterr()
    monkeypatch.setattr(search, "rank_references", lambda *a, **k: pytest.fail("described the images"))
    argv = [
        "match",
        "--reference",
        str(ref),
        "--query",
        str(qry),
        "--method",
        "precomputed",
        "--vectors",
        str(vectors),
        "--workers",
        "0",
        *[a.format(tmp=tmp_path) for a in outputs],
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and message.format(tmp=tmp_path) in err and err.count("\n") == 1
    assert vectors.read_bytes() == before and not (tmp_path / "p.txt").exists() and not (tmp_path / "m.csv").exists()


def test_match_pairs_out_with_a_name_holding_odd_characters(tmp_path):
    from fdnet.descriptors.hloc_formats import read_pairs

    ref, qry = _pairs_route(tmp_path, n=3)
    for folder in (ref, qry):
        (folder / "frame_001.png").rename(folder / "-=@frame_001.png")
    pairs = tmp_path / "-pairs list @x=1.txt"
    assert (
        main(
            [
                "match",
                "--reference",
                str(ref),
                "--query",
                str(qry),
                "--method",
                "raw",
                "--workers",
                "0",
                f"--pairs-out={pairs}",
            ]
        )
        == 0
    )
    assert ("now/-=@frame_001.png", "map/-=@frame_001.png") in read_pairs(pairs)
