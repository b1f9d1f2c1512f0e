"""`fdnet evaluate` in-process: both input modes, JSON keys, plots and bad-input errors."""

from __future__ import annotations

import json
import pickle
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from PIL import Image

from fdnet.cli import main
from fdnet.descriptors import registry
from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.descriptors.settings import MethodSettings

from conftest import require_shared, write_day_dusk_route

REQUIRED = {
    "recall_at_100_precision",
    "precision_at_max_recall",
    "auc_pr",
    "recall_at_n",
    "protocol",
    "method",
    "num_queries",
}


@dataclass(frozen=True)
class TinyPixelsSettings(MethodSettings):
    method: ClassVar[str] = "tiny-pixels"
    #: side of the square grey thumbnail
    size: int = 8

    def check(self) -> None:
        self.need_whole("size", minimum=1)


class TinyPixels(Descriptor):
    """Mean-centred 8x8 grey pixels compared by cosine (a stand-in method for CLI tests)."""

    name = "tiny-pixels"

    Settings: ClassVar[type] = TinyPixelsSettings

    def __init__(self, settings: TinyPixelsSettings | None = None, **options):
        self.conf = TinyPixelsSettings.build(settings, options)
        self.input_size = (int(self.conf.size), int(self.conf.size))

    @property
    def dim(self) -> int:
        return self.input_size[0] * self.input_size[1]

    def settings(self) -> dict:
        return {"input_size": list(self.input_size)}

    def describe(self, images):
        grey = images.mean(axis=3).reshape(len(images), -1)
        return l2_normalize(grey - grey.mean(axis=1, keepdims=True))


@pytest.fixture
def tiny_method(monkeypatch):
    # registered under this module's import name so `--method tiny-pixels` resolves through the registry
    monkeypatch.setitem(
        registry._METHODS, "tiny-pixels", registry.MethodSpec("tiny-pixels", "test stand-in", f"{__name__}:TinyPixels")
    )
    return "tiny-pixels"


@pytest.fixture
def route(tmp_path, rng):
    return write_day_dusk_route(tmp_path / "route", rng)


@pytest.fixture
def matrix_files(tmp_path):
    # 4 queries x 5 references; best matches 0 (correct), 4 (wrong), 2 (correct), 3 (correct)
    s = np.full((4, 5), 0.1)
    s[0, 0], s[1, 4], s[1, 1], s[2, 2], s[3, 3] = 0.9, 0.8, 0.5, 0.7, 0.6
    npy = tmp_path / "toy_similarity.npy"
    np.save(npy, s)
    csv = tmp_path / "gt.csv"
    csv.write_text("query_index,reference_indices\n0,0\n1,1\n2,2\n3,3\n")
    return npy, csv


def test_similarity_mode_json(matrix_files, tmp_path, capsys):
    npy, csv = matrix_files
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "evaluate",
                "--similarity",
                str(npy),
                "--ground-truth",
                str(csv),
                "--protocol",
                "vprbench",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "protocol: vprbench" in printed and "toy" in printed
    result = json.loads(out.read_text())["results"][0]
    assert REQUIRED <= set(result)
    assert result["method"] == "toy" and result["protocol"] == "vprbench" and result["num_queries"] == 4
    assert set(result["recall_at_n"]) == {"1", "5", "10", "20"}
    assert result["recall_at_n"]["1"] == 0.75
    # worked by hand in tests/evaluation/test_metrics.py::test_vprbench_by_hand
    assert result["auc_pr"] == pytest.approx(1 / 3 + 1 / 3 * (0.5 + 2 / 3) / 2 + 1 / 3 * (2 / 3 + 0.75) / 2)
    assert result["recall_at_100_precision"] == pytest.approx(1 / 3)


def test_similarity_mode_thresholds_and_distance(matrix_files, tmp_path):
    npy, csv = matrix_files
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "evaluate",
                "--similarity",
                str(npy),
                "--ground-truth",
                str(csv),
                "--thresholds",
                "2",
                "--accept",
                "raw",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    result = json.loads(out.read_text())["results"][0]
    assert result["protocol"] == "recall-over-queries" and result["thresholds"] == "2 uniform"
    assert result["auc_pr"] == pytest.approx(0.25 + 0.5 * (1 + 0.75) / 2)
    dist = tmp_path / "dist.npy"
    np.save(dist, -np.load(npy))
    out2 = tmp_path / "d.json"
    assert (
        main(
            [
                "evaluate",
                "--similarity",
                str(dist),
                "--distance",
                "--ground-truth",
                str(csv),
                "--thresholds",
                "2",
                "--accept",
                "raw",
                "--json",
                str(out2),
            ]
        )
        == 0
    )
    assert json.loads(out2.read_text())["results"][0]["auc_pr"] == result["auc_pr"]


def _error(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def test_bad_similarity_files(matrix_files, tmp_path, capsys):
    npy, csv = matrix_files
    gt = ["--ground-truth", str(csv)]
    missing = tmp_path / "missing.npy"
    assert f"{missing}: similarity file not found" in _error(capsys, ["evaluate", "--similarity", str(missing), *gt])

    flat = tmp_path / "flat.npy"
    np.save(flat, np.zeros(20))
    assert "expected a 2-D" in _error(capsys, ["evaluate", "--similarity", str(flat), *gt])

    nan = tmp_path / "nan.npy"
    s = np.load(npy)
    s[2, 3] = np.nan
    np.save(nan, s)
    err = _error(capsys, ["evaluate", "--similarity", str(nan), *gt])
    assert str(nan) in err and "NaN" in err and "query 2, reference 3" in err

    objects = tmp_path / "objects.npy"
    np.save(objects, np.array([[{"a": 1}]], dtype=object), allow_pickle=True)
    err = _error(capsys, ["evaluate", "--similarity", str(objects), *gt])
    assert str(objects) in err and "never unpickled" in err

    pickled = tmp_path / "pickled.npy"
    pickled.write_bytes(pickle.dumps({"not": "an array"}))
    assert f"{pickled}: not a .npy file" in _error(capsys, ["evaluate", "--similarity", str(pickled), *gt])

    archive = tmp_path / "archive.npz"
    np.savez(archive, s=np.zeros((4, 5)))
    assert "npz archive" in _error(capsys, ["evaluate", "--similarity", str(archive), *gt])

    truncated = tmp_path / "truncated.npy"
    truncated.write_bytes(npy.read_bytes()[:100])
    assert f"{truncated}: not a readable .npy file" in _error(capsys, ["evaluate", "--similarity", str(truncated), *gt])

    wrong_shape = tmp_path / "wrong.npy"
    np.save(wrong_shape, np.zeros((3, 5)))
    err = _error(capsys, ["evaluate", "--similarity", str(wrong_shape), *gt])
    assert f"{csv}, line 5: query index 3 out of range" in err  # the CSV has more queries than rows

    narrow = tmp_path / "narrow.npy"
    np.save(narrow, np.zeros((4, 3)))
    err = _error(capsys, ["evaluate", "--similarity", str(narrow), *gt])
    assert str(csv) in err and "out of range" in err

    bad_csv = tmp_path / "bad.csv"
    bad_csv.write_text("query_index,reference_indices\n0,zero\n")
    err = _error(capsys, ["evaluate", "--similarity", str(npy), "--ground-truth", str(bad_csv)])
    assert f"{bad_csv}, line 2" in err


def test_bad_combinations(matrix_files, route, capsys):
    npy, csv = matrix_files
    assert "nothing to evaluate" in _error(capsys, ["evaluate", "--ground-truth", str(csv)])
    assert "either --similarity" in _error(capsys, ["evaluate", "--similarity", str(npy), "--method", "raw"])
    assert "needs ground truth" in _error(capsys, ["evaluate", "--similarity", str(npy)])
    assert "recall-over-queries only" in _error(
        capsys,
        [
            "evaluate",
            "--similarity",
            str(npy),
            "--ground-truth",
            str(csv),
            "--protocol",
            "vprbench",
            "--thresholds",
            "500",
        ],
    )
    assert "unknown method 'nope'" in _error(
        capsys, ["evaluate", "--data", str(route), "--reference", "day", "--query", "dusk", "--method", "nope"]
    )
    err = _error(
        capsys, ["evaluate", "--data", str(route), "--reference", "day", "--query", "night", "--method", "raw"]
    )
    assert "night" in err and "condition folder not found" in err
    # a sequence length was silently ignored with a precomputed matrix
    assert "--sequence-length applies to --method" in _error(
        capsys, ["evaluate", "--similarity", str(npy), "--ground-truth", str(csv), "--sequence-length", "3"]
    )
    assert "--sequence-length must be a whole number of frames, at least 1" in _error(
        capsys,
        [
            "evaluate",
            "--data",
            str(route),
            "--reference",
            "day",
            "--query",
            "dusk",
            "--method",
            "raw",
            "--sequence-length=-3",
        ],
    )


def test_method_mode_several_methods_json_and_plots(tiny_method, route, tmp_path, capsys):
    out = tmp_path / "several.json"
    plots = tmp_path / "plots"
    argv = [
        "evaluate",
        "--data",
        str(route),
        "--reference",
        "day",
        "--query",
        "dusk",
        "--method",
        f"{tiny_method},raw",
        "--method-set",
        f"{tiny_method}:size=4",
        "--tolerance",
        "0",
        "--threads",
        "1",
        "--json",
        str(out),
        "--plots",
        str(plots),
    ]
    assert main(argv) == 0
    table = capsys.readouterr().out
    assert "protocol: recall-over-queries" in table and "ms/image" in table
    results = json.loads(out.read_text())["results"]
    assert len(results) == 2 and all(REQUIRED <= set(r) for r in results)
    assert results[0]["settings"]["input_size"] == [4, 4]
    assert results[0]["num_queries"] == 10 and results[0]["timing"]["ms_per_image"] >= 0
    names = {p.name for p in plots.iterdir()}
    assert {"pr_curves.png", "similarity_tiny-pixels.png", "matches_tiny-pixels.png"} <= names


def test_two_models_of_one_method_compare_side_by_side_under_labels(tiny_method, route, tmp_path, capsys):
    """--method LABEL=METHOD names each row; each label takes its own options (here two sizes of
    one stand-in method: two ONNX models or two runs are given the same way)."""
    out = tmp_path / "labelled.json"
    argv = [
        "evaluate",
        "--data",
        str(route),
        "--reference",
        "day",
        "--query",
        "dusk",
        "--tolerance",
        "0",
        "--method",
        f"small={tiny_method},large={tiny_method},raw",
        "--method-set",
        "small:size=4",
        "--method-set",
        "large:size=8",
        "--threads",
        "1",
        "--json",
        str(out),
    ]
    assert main(argv) == 0
    table = capsys.readouterr().out
    assert "small" in table and "large" in table
    results = json.loads(out.read_text())["results"]
    assert [r["method"] for r in results] == ["small", "large", "raw"]
    assert [r["settings"].get("method") for r in results] == [tiny_method, tiny_method, None]
    assert [r["settings"]["input_size"] for r in results[:2]] == [[4, 4], [8, 8]]
    for bad, message in (
        (f"raw={tiny_method}", "the label 'raw' is another method's name"),
        ("a b=raw", "a label is letters, digits"),
        ("x=nosuch", "unknown method 'nosuch'"),
    ):
        err = _error(
            capsys, ["evaluate", "--data", str(route), "--reference", "day", "--query", "dusk", "--method", bad]
        )
        assert err.startswith("fdnet evaluate: error: ") and message in err


def test_methods_that_cannot_be_told_apart_are_refused(tiny_method, route, tmp_path, capsys):
    """A method named twice gave two identical rows under one name (the last --weights METHOD: for
    both); two values of one option for one method kept only one of them. Both are refused
    before any image is described, and nothing is written."""
    out = tmp_path / "r.json"
    base = ["evaluate", "--data", str(route), "--reference", "day", "--query", "dusk", "--json", str(out)]
    err = _error(capsys, [*base, "--method", f"{tiny_method},raw,{tiny_method}"])
    assert err.startswith("fdnet evaluate: error: --method names tiny-pixels more than once")
    assert "give each its own label" in err and not out.exists()
    (tmp_path / "a.onnx").write_bytes(b"a")
    (tmp_path / "b.onnx").write_bytes(b"b")
    err = _error(
        capsys,
        [
            *base,
            "--method",
            "onnx",
            "--weights",
            f"onnx:{tmp_path / 'a.onnx'}",
            "--weights",
            f"onnx:{tmp_path / 'b.onnx'}",
        ],
    )
    assert err.startswith("fdnet evaluate: error: --weights gives onnx 2 values") and not out.exists()
    err = _error(
        capsys,
        [
            *base,
            "--method",
            "onnx,onnx",
            "--weights",
            f"onnx:{tmp_path / 'a.onnx'}",
            "--weights",
            f"onnx:{tmp_path / 'b.onnx'}",
        ],
    )
    assert "--method names onnx more than once" in err and not out.exists()


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--predictions", "2"], "--predictions K needs --json FILE"),
        (["--no-curve"], "--no-curve needs --json FILE"),
        (["--examples", "3"], "--examples N needs --plots DIR"),
        (["--name", "mine"], "--name needs --similarity FILE.npy"),
        (["--distance"], "--distance needs --similarity FILE.npy"),
    ],
)
def test_a_flag_whose_output_has_nowhere_to_go_is_refused(tiny_method, route, capsys, extra, message):
    """--predictions without --json (and the like) was ignored without a word."""
    err = _error(
        capsys,
        ["evaluate", "--data", str(route), "--reference", "day", "--query", "dusk", "--method", tiny_method, *extra],
    )
    assert err.startswith(f"fdnet evaluate: error: {message}") and "would do nothing" in err


def test_method_mode_frames_and_explicit_ground_truth(tiny_method, route, tmp_path):
    # explicit list: query i matches reference i (full-traverse indices), sliced by --frames 2:8
    csv = tmp_path / "gt.csv"
    csv.write_text("query_index,reference_indices\n" + "".join(f"{i},{i}\n" for i in range(10)))
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(route),
                "--reference",
                "day",
                "--query",
                "dusk",
                "--method",
                tiny_method,
                "--ground-truth",
                str(csv),
                "--frames",
                "2:8",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    result = json.loads(out.read_text())["results"][0]
    assert result["num_queries"] == 6 and result["num_references"] == 6
    assert result["recall_at_n"]["1"] == 1.0 and result["recall_at_100_precision"] == 1.0


@pytest.mark.shared_data
def test_corridor_vprbench_hog_through_the_cli(tmp_path):
    corridor = require_shared("corridor")
    out = tmp_path / "hog.json"
    assert (
        main(
            [
                "evaluate",
                "--similarity",
                str(corridor / "vprbench_precomputed" / "HOG_similarity.npy"),
                "--ground-truth",
                str(corridor / "ground_truth.csv"),
                "--protocol",
                "vprbench",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    result = json.loads(out.read_text())["results"][0]
    assert round(result["auc_pr"], 3) == 0.697 and round(result["top1_accuracy"], 3) == 0.477


@pytest.mark.shared_data
def test_gardens_point_slice(tiny_method, tmp_path):
    gardens = require_shared("gardens_point")
    out = tmp_path / "gp.json"
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(gardens),
                "--reference",
                "day_right",
                "--query",
                "night_right",
                "--method",
                tiny_method,
                "--method-set",
                "size=16",
                "--frames",
                "100:140",
                "--tolerance",
                "2",
                "--threads",
                "1",
                "--accept",
                "raw",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    result = json.loads(out.read_text())["results"][0]
    assert result["num_queries"] == 40 and result["num_references"] == 40
    assert "tolerance 2" in result["ground_truth"]

    # the same numbers straight from the descriptor's similarity matrix and frame-aligned truth
    from fdnet.data.groundtruth import GroundTruth
    from fdnet.data.images import list_images
    from fdnet.descriptors.base import describe_paths
    from fdnet.metrics import evaluate_similarity

    d = TinyPixels(size=16)
    q = describe_paths(d, list_images(gardens / "night_right")[100:140])
    r = describe_paths(d, list_images(gardens / "day_right")[100:140])
    direct = evaluate_similarity(q @ r.T, GroundTruth.aligned(40, 40, 2))
    assert result["recall_at_n"] == {str(k): pytest.approx(v) for k, v in direct.recall_at_n.items()}
    assert result["auc_pr"] == pytest.approx(direct.auc_pr, abs=1e-6)


def test_evaluate_with_dataset_format_vprbench_corridor(tmp_path):
    from conftest import require_shared

    corridor = require_shared("corridor")
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(corridor),
                "--dataset-format",
                "vprbench",
                "--method",
                "raw",
                "--protocol",
                "vprbench",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    result = json.loads(out.read_text())["results"][0]
    assert result["num_queries"] == 111 and result["protocol"] == "vprbench"


def test_split_without_dataset_format_is_an_error(tmp_path, capsys):
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(tmp_path),
                "--reference",
                "a",
                "--query",
                "b",
                "--method",
                "raw",
                "--split",
                "test",
            ]
        )
        == 2
    )
    assert "--dataset-format" in capsys.readouterr().err


def test_filter_frames_drops_dark_frames_from_both_conditions(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("FDNET_CACHE", str(tmp_path / "cache"))  # the filter caches what it kept
    rng = np.random.default_rng(0)
    for cond in ("a", "b"):
        (tmp_path / cond).mkdir()
        for i in range(12):
            level = 0.0 if i in (3, 4) else 1.0  # frames 3 and 4 are a "tunnel"
            img = (rng.integers(0, 256, (16, 32, 3)) * level).astype(np.uint8)
            Image.fromarray(img).save(tmp_path / cond / f"f{i:02d}.png")
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(tmp_path),
                "--reference",
                "a",
                "--query",
                "b",
                "--method",
                "raw",
                "--filter-frames",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    assert json.loads(out.read_text())["results"][0]["num_queries"] == 10
    assert "dropped 2 dark" in capsys.readouterr().err
    assert len(list((tmp_path / "cache" / "filters").iterdir())) == 1


# ----------------------------------------------------------------------------- image order and ground truth


def _write_grey(path, pixels):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels).save(path)


def _text_order(names):
    return sorted(names)


@pytest.mark.parametrize("reference_rows, query_rows", [("natural", "natural"), ("text", "natural")])
def test_unpadded_names_ground_truth_from_positions_end_to_end(tmp_path, reference_rows, query_rows):
    """frame_1 ... frame_12 (natural order differs from text order). The query traverse drives the
    route backwards, so query frame_k is at the place of reference frame_(13-k); three queries
    show a look-alike of another place. `fdnet groundtruth --positions` then `fdnet evaluate
    --ground-truth` must pair every query with its own place: R@1 = 9/12, whatever order the
    position files list their rows in."""
    n = 12
    rng = np.random.default_rng(3)
    places = [rng.integers(0, 256, (32, 64), dtype=np.uint8) for _ in range(n)]  # distinct views
    names = [f"frame_{k}.png" for k in range(1, n + 1)]
    true_place = {k: n - k for k in range(1, n + 1)}  # 0-based place of query frame_k
    shown_place = dict(true_place)
    for k in (2, 5, 11):  # look-alikes: top-1 will be wrong
        shown_place[k] = (true_place[k] + 6) % n
    route = tmp_path / "route"
    for k in range(1, n + 1):
        _write_grey(route / "ref" / f"frame_{k}.png", places[k - 1])
        _write_grey(route / "qry" / f"frame_{k}.png", (places[shown_place[k]] * 0.8).astype(np.uint8))

    def position_file(path, row_order, easting_of):
        listed = names if row_order == "natural" else _text_order(names)
        path.write_text(
            "image,easting,northing\n"
            + "".join(f"{name},{500000 + easting_of(int(name[6:-4]))},6000000\n" for name in listed)
        )
        return str(path)

    ref_csv = position_file(tmp_path / "ref.csv", reference_rows, lambda k: 10 * (k - 1))
    qry_csv = position_file(tmp_path / "qry.csv", query_rows, lambda k: 10 * true_place[k])
    gt = tmp_path / "gt.csv"
    assert main(["groundtruth", "--positions", ref_csv, qry_csv, "--tolerance-m", "4", "--out", str(gt)]) == 0
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(route),
                "--reference",
                "ref",
                "--query",
                "qry",
                "--method",
                "raw",
                "--ground-truth",
                str(gt),
                "--json",
                str(out),
            ]
        )
        == 0
    )
    expected = np.mean([shown_place[k] == true_place[k] for k in range(1, n + 1)])
    assert expected == 0.75
    assert json.loads(out.read_text())["results"][0]["recall_at_n"]["1"] == pytest.approx(expected)


def test_dataset_format_with_missing_ground_truth_file_is_an_error(route, capsys):
    missing = route.parent / "missing.csv"
    err = _error(
        capsys,
        [
            "evaluate",
            "--data",
            str(route),
            "--dataset-format",
            "folders",
            "--reference",
            "day",
            "--query",
            "dusk",
            "--method",
            "raw",
            "--ground-truth",
            str(missing),
        ],
    )
    assert f"{missing}: ground-truth file not found" in err


def test_dataset_format_uses_the_given_ground_truth(tiny_method, route, tmp_path):
    def r_at_1(*extra):
        out = tmp_path / "r.json"
        assert (
            main(
                [
                    "evaluate",
                    "--data",
                    str(route),
                    "--dataset-format",
                    "folders",
                    "--reference",
                    "day",
                    "--query",
                    "dusk",
                    "--method",
                    tiny_method,
                    "--json",
                    str(out),
                    *extra,
                ]
            )
            == 0
        )
        return json.loads(out.read_text())["results"][0]

    assert r_at_1()["recall_at_n"]["1"] == 1.0  # frame-aligned: every top-1 is right
    shifted = tmp_path / "shifted.csv"  # query i is place i+1: none is
    shifted.write_text("query_index,reference_indices\n" + "".join(f"{i},{(i + 1) % 10}\n" for i in range(10)))
    result = r_at_1("--ground-truth", str(shifted))
    assert result["recall_at_n"]["1"] == 0.0 and "shifted.csv" in result["ground_truth"]
    # over the chosen split: 4 queries x 4 references, the list's indices are the split's
    part = tmp_path / "part.csv"
    part.write_text("query_index,reference_indices\n0,0\n1,1\n2,3\n3,2\n")
    result = r_at_1("--split", "3:7", "--ground-truth", str(part))
    assert (result["num_queries"], result["num_references"]) == (4, 4)
    assert result["recall_at_n"]["1"] == 0.5


def test_dataset_format_ground_truth_sized_for_another_split_is_an_error(route, tmp_path, capsys):
    full = tmp_path / "full.csv"
    full.write_text("query_index,reference_indices\n" + "".join(f"{i},{i}\n" for i in range(10)))
    err = _error(
        capsys,
        [
            "evaluate",
            "--data",
            str(route),
            "--dataset-format",
            "folders",
            "--reference",
            "day",
            "--query",
            "dusk",
            "--split",
            "0:5",
            "--method",
            "raw",
            "--ground-truth",
            str(full),
        ],
    )
    assert f"{full}, line 7: query index 5 out of range (0..4)" in err


def test_ground_truth_names_that_do_not_match_the_folders_are_an_error(route, tmp_path, capsys):
    from fdnet.data.groundtruth import GroundTruth

    names = [f"{i:03d}.png" for i in range(10)]
    gt = tmp_path / "gt.csv"
    # what `fdnet groundtruth` writes for a query folder listed in the opposite order
    gt.write_text(
        "query_index,reference_indices,query_name,reference_names\n"
        + "".join(f"{i},{i},{names[::-1][i]},{names[i]}\n" for i in range(10))
    )
    err = _error(
        capsys,
        [
            "evaluate",
            "--data",
            str(route),
            "--reference",
            "day",
            "--query",
            "dusk",
            "--method",
            "raw",
            "--ground-truth",
            str(gt),
        ],
    )
    assert f"{gt}, line 2: query 0 is '009.png' in the ground truth but '000.png' in {route / 'dusk'}" in err
    err = _error(
        capsys,
        [
            "evaluate",
            "--data",
            str(route),
            "--dataset-format",
            "folders",
            "--reference",
            "day",
            "--query",
            "dusk",
            "--method",
            "raw",
            "--ground-truth",
            str(gt),
        ],
    )
    assert f"{gt}, line 2: query 0 is '009.png'" in err
    # the same names in the right order are accepted
    GroundTruth.aligned(10, 10, 0).to_csv(gt, query_names=names, reference_names=names)
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(route),
                "--reference",
                "day",
                "--query",
                "dusk",
                "--method",
                "raw",
                "--ground-truth",
                str(gt),
            ]
        )
        == 0
    )


def test_similarity_with_a_forged_header_is_refused(matrix_files, tmp_path, capsys):
    _, csv = matrix_files
    forged = tmp_path / "forged.npy"
    with open(forged, "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, {"descr": "<f4", "fortran_order": False, "shape": (10**6, 10**6)})
        handle.write(b"\0" * 16)
    err = _error(capsys, ["evaluate", "--similarity", str(forged), "--ground-truth", str(csv)])
    assert str(forged) in err and "(1000000, 1000000)" in err and "3.6 TiB" in err


@pytest.mark.parametrize("option", ["--json", "--plots"])
def test_unwritable_outputs_fail_before_any_work(route, tmp_path, capsys, monkeypatch, option):
    import fdnet.evaluation.experiment as experiment

    def no_work(*args, **kwargs):
        raise AssertionError("the evaluation ran before the output path was checked")

    monkeypatch.setattr(experiment, "evaluate_method", no_work)
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    target = blocker / "results"  # its parent is a regular file: nothing can be created there
    err = _error(
        capsys,
        [
            "evaluate",
            "--data",
            str(route),
            "--reference",
            "day",
            "--query",
            "dusk",
            "--method",
            "raw",
            option,
            str(target),
        ],
    )
    assert str(target.parent) in err and "cannot create" in err


def test_filter_frames_with_a_format_that_has_no_filter_is_an_error(route, capsys):
    # ignored silently, the numbers would be for unfiltered frames
    err = _error(
        capsys,
        [
            "evaluate",
            "--data",
            str(route),
            "--dataset-format",
            "folders",
            "--reference",
            "day",
            "--query",
            "dusk",
            "--method",
            "raw",
            "--filter-frames",
        ],
    )
    assert "--filter-frames: the folders format has no frame filter" in err


def test_accept_rules_json_and_table(matrix_files, tmp_path, capsys):
    npy, csv = matrix_files
    out = tmp_path / "one.json"
    # by default the field's protocol (raw: the best-match score) is the headline, fdnet's margin rule beside
    # it. margin: best minus the best outside radius 1 -> q0 .8 (right), q1 .3 (wrong: 4 vs its true 1 at
    # .5), q2 .6, q3 .5 -> the wrong one is the least confident: R@100P 3/4 (raw: 1/4)
    assert (
        main(
            [
                "evaluate",
                "--similarity",
                str(npy),
                "--ground-truth",
                str(csv),
                "--accept-set",
                "radius=1",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "raw is the field's protocol" in printed and "margin is an fdnet acceptance rule" in printed
    one = json.loads(out.read_text())["results"][0]
    assert one["acceptance"] == "raw" and one["recall_at_100_precision"] == pytest.approx(0.25)
    margin = one["per_acceptance"]["margin"]
    assert margin["settings"]["margin"]["radius"] == 1
    assert margin["recall_at_100_precision"] == pytest.approx(0.75)
    assert margin["recall_at_99_precision"] == pytest.approx(0.75)
    assert (
        main(
            [
                "evaluate",
                "--similarity",
                str(npy),
                "--ground-truth",
                str(csv),
                "--accept",
                "margin",
                "--accept-set",
                "radius=1",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    alone = json.loads(out.read_text())["results"][0]
    assert alone["acceptance"] == "margin" and alone["recall_at_100_precision"] == pytest.approx(0.75)
    assert "per_acceptance" not in alone
    capsys.readouterr()
    several = tmp_path / "several.json"
    assert (
        main(
            [
                "evaluate",
                "--similarity",
                str(npy),
                "--ground-truth",
                str(csv),
                "--accept",
                "raw,margin,ratio",
                "--accept-set",
                "radius=0",
                "--json",
                str(several),
            ]
        )
        == 0
    )
    table = capsys.readouterr().out
    rows = {line.split()[1]: line.split() for line in table.splitlines() if line.startswith("toy ")}
    assert set(rows) == {"raw", "margin", "ratio"} and rows["raw"][6] == "0.250" and rows["margin"][6] == "0.750"
    doc = json.loads(several.read_text())["results"][0]
    assert doc["acceptance"] == "raw" and doc["recall_at_100_precision"] == pytest.approx(0.25)
    per = doc["per_acceptance"]
    assert per["margin"]["recall_at_100_precision"] == pytest.approx(0.75)
    assert per["margin"]["settings"] == {"margin": {"radius": 0, "radius_s": None, "radius_m": None, "depth": None}}
    # ratio 1 - (1 - best) / (1 - outside): q0 1 - .1/.9 = .89, q2 1 - .3/.9 = .67, q1 (wrong) 1 - .2/.5 = .6,
    # q3 1 - .4/.9 = .56 -> R@100P 2/4
    assert per["ratio"]["recall_at_100_precision"] == pytest.approx(0.5)
    assert doc["recall_at_n"]["1"] == 0.75  # ranking does not depend on the rule


def test_sequence_matching_with_the_margin_rule(tiny_method, route, tmp_path):
    out = tmp_path / "seq.json"
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(route),
                "--reference",
                "day",
                "--query",
                "dusk",
                "--method",
                tiny_method,
                "--sequence-length",
                "3",
                "--accept",
                "margin,raw",
                "--accept-set",
                "radius=1",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    result = json.loads(out.read_text())["results"][0]
    assert result["acceptance"] == "margin" and result["settings"]["sequence_length"] == 3
    assert set(result["per_acceptance"]) == {"margin", "raw"}


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--accept", "best"], "unknown acceptance rule 'best'"),
        (["--accept", "margin", "--accept-set", "radius=-2"], "radius=-2: must be an integer >= 0"),
        (["--accept", "raw", "--accept-set", "radius=2"], "no setting 'radius' in rule raw"),
        (["--accept", "floor"], "is a gate"),
    ],
)
def test_bad_acceptance_rules_are_errors(matrix_files, capsys, extra, message):
    npy, csv = matrix_files
    err = _error(capsys, ["evaluate", "--similarity", str(npy), "--ground-truth", str(csv), *extra])
    assert err.startswith("fdnet evaluate: error: ") and message in err


@pytest.mark.parametrize("frames", ["5:50", "10:", "12:20"])
def test_a_frame_range_past_the_folders_end_is_refused(route, tiny_method, capsys, frames):
    err = _error(
        capsys,
        [
            "evaluate",
            "--data",
            str(route),
            "--reference",
            "day",
            "--query",
            "dusk",
            "--method",
            tiny_method,
            "--frames",
            frames,
        ],
    )
    assert f"--frames {frames}: past the end of the folders (day 10, dusk 10 images)" in err


def test_a_frame_range_inside_the_folders_is_evaluated(route, tiny_method, tmp_path):
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(route),
                "--reference",
                "day",
                "--query",
                "dusk",
                "--method",
                tiny_method,
                "--frames",
                "5:10",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    assert json.loads(out.read_text())["results"][0]["num_queries"] == 5


def test_one_json_schema_with_predictions_and_a_paper_table(matrix_files, tmp_path, capsys):
    """One method or several: the same document (format, fdnet version, command, settings, a list
    of results); --predictions adds each query's best references; --table prints a table to paste."""
    npy, csv = matrix_files
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "evaluate",
                "--similarity",
                str(npy),
                "--ground-truth",
                str(csv),
                "--json",
                str(out),
                "--predictions",
                "2",
                "--table",
                "markdown",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "| method | accept | data | R@1 | R@100P | AUC-PR |" in printed and "| toy | raw |" in printed
    doc = json.loads(out.read_text())
    assert (doc["format"], doc["format_version"]) == ("fdnet-evaluation", 2) and doc["fdnet_version"]
    assert doc["protocol"] == "recall-over-queries" and doc["settings"]["predictions"] == 2
    assert isinstance(doc["results"], list) and len(doc["results"]) == 1
    first = doc["results"][0]["predictions"][0]
    assert set(first) >= {"query_index", "top", "scores", "correct"} and len(first["top"]) == 2
    assert first["correct"][0] is True  # query 0's best is its true place (see the matrix above)
    assert main(["evaluate", "--similarity", str(npy), "--ground-truth", str(csv), "--table", "latex"]) == 0
    latex = capsys.readouterr().out
    assert "\\begin{tabular}{lllrrr}" in latex and "toy & raw &" in latex and "\\end{tabular}" in latex
