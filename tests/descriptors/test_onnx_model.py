"""`--method onnx`: any ONNX model as a descriptor (fdnet.descriptors.onnx_model)."""

import json
import warnings

import numpy as np
import pytest

from fdnet.cli import main
from fdnet.descriptors import create
from fdnet.errors import ConfigError, DataError

from conftest import read_csv_rows, require_shared, write_random_places

onnxruntime = pytest.importorskip("onnxruntime", reason="optional extra fdnet[onnx] not installed")
torch = pytest.importorskip("torch")


class MeanConv(torch.nn.Module):
    """(N, 3, H, W) -> (N, 8): a convolution averaged over the image; any input size."""

    def __init__(self, seed=0):
        super().__init__()
        torch.manual_seed(seed)
        self.conv = torch.nn.Conv2d(3, 8, 3, padding=1)

    def forward(self, x):
        return self.conv(x).mean(dim=(2, 3))


def export(module, path, size=(16, 32), dynamic_size=False, output="vectors"):
    axes = {"images": {0: "n", **({2: "h", 3: "w"} if dynamic_size else {})}, output: {0: "n"}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module.eval(),
            (torch.rand(1, 3, *size),),
            str(path),
            input_names=["images"],
            output_names=[output],
            dynamic_axes=axes,
            opset_version=17,
            dynamo=False,
        )
    return path


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("onnx")
    assert main(["synth", "--out", str(root / "route"), "--num-frames", "12", "--conditions", "summer,night"]) == 0
    assert (
        main(["train", "--data", str(root / "route"), "--preset", "tiny", "--out", str(root / "run"), "--no-progress"])
        == 0
    )
    assert main(["export", "--checkpoint", str(root / "run"), "--out", str(root / "fdnet.onnx")]) == 0
    return root / "run", root / "fdnet.onnx"


def test_an_exported_fdnet_reads_back_with_no_settings_and_gives_its_vectors_on_real_images(tiny_run, tmp_path):
    run, model = tiny_run
    images = require_shared("gardens_point", "day_left")
    onnx = create("onnx", weights=str(model))
    fdnet = create("fdnet", checkpoint=str(run), device="cpu")
    assert onnx.input_size == tuple(fdnet.input_size) and onnx.dim == fdnet.dim  # from the model's metadata
    out = {}
    for name, options in (("onnx", ["--weights", str(model)]), ("fdnet", ["--checkpoint", str(run), "--fp32"])):
        assert (
            main(
                [
                    "extract",
                    "--method",
                    name,
                    *options,
                    "--images",
                    str(images),
                    "--out",
                    str(tmp_path / f"{name}.npz"),
                    "--workers",
                    "0",
                ]
            )
            == 0
        )
        with np.load(tmp_path / f"{name}.npz") as data:
            out[name] = data["descriptors" if name == "onnx" else "content"]
    assert out["onnx"].shape == out["fdnet"].shape == (200, fdnet.dim)
    np.testing.assert_allclose(out["onnx"], out["fdnet"], atol=1e-4)


def test_evaluate_gives_the_same_numbers_through_onnx_as_through_pytorch(tiny_run, tmp_path, capsys):
    run, model = tiny_run
    data = require_shared("gardens_point")
    common = [
        "evaluate",
        "--data",
        str(data),
        "--reference",
        "day_left",
        "--query",
        "night_right",
        "--frames",
        "100:140",
    ]
    assert main([*common, "--method", "onnx", "--weights", str(model), "--json", str(tmp_path / "o.json")]) == 0
    assert main([*common, "--method", "fdnet", "--checkpoint", str(run), "--json", str(tmp_path / "f.json")]) == 0
    o, f = (json.loads((tmp_path / n).read_text())["results"][0] for n in ("o.json", "f.json"))
    assert o["recall_at_n"] == pytest.approx(f["recall_at_n"], abs=0.01)
    for key in ("recall_at_100_precision", "auc_pr", "precision_at_max_recall"):
        assert o[key] == pytest.approx(f[key], abs=0.01), key


def test_preprocessing_settings_are_applied_as_documented(tmp_path):
    path = export(MeanConv(), tmp_path / "m.onnx", dynamic_size=True)
    module = MeanConv()
    images = np.random.default_rng(0).random((3, 16, 32, 3), dtype=np.float32)
    mean, std = [0.485, 0.456, 0.406], [0.229, 0.224, 0.225]
    d = create("onnx", weights=str(path), input_size="16x32", mean=mean, std=std, channels="bgr", normalise="none")
    prepared = (images[..., ::-1] - np.float32(mean)) / np.float32(std)
    with torch.no_grad():
        expected = module(torch.from_numpy(np.ascontiguousarray(prepared.transpose(0, 3, 1, 2)))).numpy()
    np.testing.assert_allclose(d.describe(images), expected, atol=1e-5)
    unit = create("onnx", weights=str(path), input_size=[16, 32])
    np.testing.assert_allclose(np.linalg.norm(unit.describe(images), axis=1), 1.0, atol=1e-6)
    assert unit.dim == 8 and unit.input_size == (16, 32)


def test_a_graph_fixed_at_batch_one_describes_any_batch(tmp_path):
    path = tmp_path / "one.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            MeanConv().eval(),
            (torch.rand(1, 3, 16, 32),),
            str(path),
            input_names=["images"],
            output_names=["v"],
            opset_version=17,
            dynamo=False,
        )
    d = create("onnx", weights=str(path))
    images = np.random.default_rng(1).random((5, 16, 32, 3), dtype=np.float32)
    one_by_one = np.concatenate([d.describe(images[i : i + 1]) for i in range(5)])
    np.testing.assert_allclose(d.describe(images), one_by_one, atol=1e-6)


@pytest.mark.parametrize(
    "case, message",
    [
        ("not_onnx", "not an ONNX model onnxruntime can load"),
        ("four_d", "a descriptor model returns (N, D) vectors"),
        ("dynamic", "input size is not fixed"),
        ("missing", "ONNX model not found"),
    ],
)
def test_bad_models_are_one_line_errors(case, message, tmp_path, capsys):
    path = tmp_path / f"{case}.onnx"
    if case == "not_onnx":
        path.write_text("this is not a model\n")
    elif case == "four_d":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(
                torch.nn.Conv2d(3, 4, 3).eval(),
                (torch.rand(1, 3, 16, 32),),
                str(path),
                input_names=["images"],
                output_names=["maps"],
                opset_version=17,
                dynamo=False,
            )
    elif case == "dynamic":
        export(MeanConv(), path, dynamic_size=True)
    images = write_random_places(tmp_path / "images", 3)
    assert (
        main(
            [
                "match",
                "--reference",
                str(images),
                "--query",
                str(images),
                "--method",
                "onnx",
                "--weights",
                str(path),
                "--out",
                str(tmp_path / "m.csv"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and message in err and str(path) in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "m.csv").exists()


def test_settings_that_contradict_the_graph_are_refused(tmp_path):
    path = export(MeanConv(), tmp_path / "fixed.onnx")
    with pytest.raises(ConfigError, match="the graph's input is 16x32"):
        create("onnx", weights=str(path), input_size="32x32")
    with pytest.raises(ConfigError, match="not HxW"):
        create("onnx", weights=str(path), input_size="big")
    with pytest.raises(ConfigError, match="channels"):
        create("onnx", weights=str(path), channels="hsv")
    with pytest.raises(ConfigError, match="not one of the model's outputs"):
        create("onnx", weights=str(path), output="logits")
    with pytest.raises(ConfigError, match="std must not be 0"):
        create("onnx", weights=str(path), std=0)


def test_the_fingerprint_covers_the_model_and_its_settings_not_its_location(tmp_path):
    a = export(MeanConv(seed=0), tmp_path / "a.onnx")
    b = export(MeanConv(seed=1), tmp_path / "b.onnx")
    moved = tmp_path / "elsewhere" / "a.onnx"
    moved.parent.mkdir()
    moved.write_bytes(a.read_bytes())
    fa = create("onnx", weights=str(a)).fingerprint()
    assert create("onnx", weights=str(moved)).fingerprint() == fa
    assert create("onnx", weights=str(b)).fingerprint() != fa
    assert create("onnx", weights=str(a), mean=0.5).fingerprint() != fa


def test_a_database_and_a_calibration_of_one_model_refuse_another(tmp_path, capsys):
    a = export(MeanConv(seed=0), tmp_path / "a.onnx")
    b = export(MeanConv(seed=1), tmp_path / "b.onnx")
    images = write_random_places(tmp_path / "map", 6)
    db = tmp_path / "map.db"
    assert (
        main(["database", "build", "--images", str(images), "--method", "onnx", "--weights", str(a), "--db", str(db)])
        == 0
    )
    assert (
        main(["database", "add", "--db", str(db), "--images", str(images), "--method", "onnx", "--weights", str(b)])
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet database: error: ") and "Traceback" not in err

    route = tmp_path / "route"
    for condition, brightness in (("day", 1.0), ("dusk", 0.8)):
        write_random_places(route / condition, 12, seed=3, brightness=brightness)
    calibration = tmp_path / "cal.yaml"
    assert (
        main(
            [
                "calibrate",
                "--data",
                str(route),
                "--reference",
                "day",
                "--query",
                "dusk",
                "--method",
                "onnx",
                "--weights",
                str(a),
                "--out",
                str(calibration),
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
                "onnx",
                "--weights",
                str(b),
                "--calibration",
                str(calibration),
                "--out",
                str(tmp_path / "m.csv"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and str(calibration) in err and "Traceback" not in err
    assert (
        main(
            [
                "match",
                "--reference",
                str(route / "day"),
                "--query",
                str(route / "dusk"),
                "--method",
                "onnx",
                "--weights",
                str(a),
                "--calibration",
                str(calibration),
                "--out",
                str(tmp_path / "m.csv"),
            ]
        )
        == 0
    )
    assert "accepted" in read_csv_rows(tmp_path / "m.csv")[0]


def test_benchmark_times_an_onnx_model_beside_the_others(tmp_path, capsys):
    path = export(MeanConv(), tmp_path / "m.onnx")
    assert (
        main(
            [
                "benchmark",
                "--parts",
                "methods",
                "--method",
                "sad",
                "--weights",
                f"onnx:{path}",
                "--num-images",
                "4",
                "--quick",
                "--json",
                str(tmp_path / "b.json"),
            ]
        )
        == 0
    )
    report = json.loads((tmp_path / "b.json").read_text())
    assert report["method_extraction_ms"]["onnx"] > 0 and report["ratio_vs_sad"]["onnx"] > 0
    assert "onnx" in capsys.readouterr().out


# ------------------------------------------------------------------ hand-built graphs (onnx.helper)
def graph_model(path, input_shape, metadata=None, dtype="float", output_shape=("n", 4), tail=(), axes=None):
    """A model that averages its input over the two image axes of ``input_shape`` (``axes``,
    default as its shape says) and maps the 3 channel means to 4 numbers; ``tail``: more nodes
    after ``v``."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    types = {"float": TensorProto.FLOAT, "uint8": TensorProto.UINT8}
    axes = axes or ([1, 2] if input_shape[-1] == 3 and input_shape[1] != 3 else [2, 3])
    channels = input_shape[-1] if axes == [1, 2] else input_shape[1]
    channels = channels if isinstance(channels, int) else 3
    nodes = [helper.make_node("Cast", ["images"], ["xf"], to=TensorProto.FLOAT)] if dtype != "float" else []
    nodes += [
        helper.make_node("ReduceMean", ["xf" if nodes else "images"], ["p"], axes=axes, keepdims=0),
        helper.make_node("MatMul", ["p", "W"], ["v"]),
        *tail,
    ]
    weights = np.arange(channels * 4, dtype=np.float32).reshape(channels, 4) / 10 + 0.1
    graph = helper.make_graph(
        nodes,
        "g",
        [helper.make_tensor_value_info("images", types[dtype], list(input_shape))],
        [helper.make_tensor_value_info(nodes[-1].output[0], TensorProto.FLOAT, list(output_shape))],
        initializer=[numpy_helper.from_array(weights, "W")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for key, value in (metadata or {}).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(model, str(path))
    return path


def match_error(tmp_path, capsys, model, *settings):
    images = tmp_path / "images"
    if not images.exists():
        write_random_places(images, 3)
    capsys.readouterr()
    code = main(
        [
            "match",
            "--reference",
            str(images),
            "--query",
            str(images),
            "--method",
            "onnx",
            "--weights",
            str(model),
            *[a for s in settings for a in ("--method-set", s)],
            "--out",
            str(tmp_path / "m.csv"),
            "--workers",
            "0",
        ]
    )
    err = capsys.readouterr().err
    return code, err


@pytest.mark.parametrize(
    "metadata, message",
    [
        ({"fdnet.input_size": "abc"}, "'abc' is not HxW"),
        ({"fdnet.mean": "[1,2]"}, "is not a number or a list of 3 numbers"),
        ({"std": "0"}, "std must not be 0"),
        ({"channels": "BGRA"}, "channels='BGRA'"),
        ({"output": "nope"}, "'nope' (model metadata output) is not one of the model's outputs"),
        ({"fdnet.mean": "[123.675,116.28,103.53]", "fdnet.std": "[58.395,57.12,57.375]"}, "not on the [0, 1] scale"),
    ],
)
def test_garbage_in_the_models_metadata_is_one_line_naming_the_model(metadata, message, tmp_path, capsys):
    model = graph_model(tmp_path / "meta model.onnx", ["n", 3, "h", "w"], {"fdnet.input_size": "16x32", **metadata})
    code, err = match_error(tmp_path, capsys, model)
    assert code == 2 and err.startswith("fdnet match: error: ") and message in err and str(model) in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "m.csv").exists()


def test_mean_and_std_on_the_0_255_scale_are_refused_not_applied_to_0_1_images(tmp_path):
    model = graph_model(tmp_path / "m.onnx", ["n", 3, 16, 32])
    with pytest.raises(ConfigError, match="divided by 255"):
        create("onnx", weights=str(model), mean=[123.675, 116.28, 103.53], std=[58.395, 57.12, 57.375])
    with pytest.raises(ConfigError, match="not on the"):
        create("onnx", weights=str(model), std=255)
    assert create("onnx", weights=str(model), mean=0.5, std=1 / 255).std[0] == pytest.approx(1 / 255)


def test_a_graph_that_does_not_say_where_the_channels_are_is_fed_nchw_with_a_warning_or_as_told(tmp_path, caplog):
    rng = np.random.default_rng(2)
    images = rng.random((5, 8, 3, 3), dtype=np.float32)  # 8x3 images: (N, 3, 8, 3) fits both layouts
    both = graph_model(tmp_path / "both.onnx", ["n", 3, 8, 3], axes=[1, 2])  # in truth NHWC, 3x8 images
    with caplog.at_level("WARNING", logger="fdnet"):
        guessed = create("onnx", weights=str(both), normalise="none")
    assert guessed.layout == "nchw" and "layout=nhwc" in caplog.text and str(both) in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="fdnet"):
        told = create("onnx", weights=str(both), layout="nhwc", normalise="none")
    assert told.layout == "nhwc" and told.input_size == (3, 8) and not caplog.text
    # as told: the channel means reach the model's channel axis (axis 3 for NHWC)
    weights = np.arange(12, dtype=np.float32).reshape(3, 4) / 10 + 0.1
    nhwc_images = rng.random((5, 3, 8, 3), dtype=np.float32)
    np.testing.assert_allclose(told.describe(nhwc_images), nhwc_images.mean(axis=(1, 2)) @ weights, rtol=1e-5)
    assert told.fingerprint() != guessed.fingerprint()  # the layout is part of what the vectors are
    assert guessed.describe(images).shape == (5, 4)
    fixed = graph_model(tmp_path / "fixed.onnx", ["n", 3, 16, 32])
    # the graph's own layout: not a setting of its own
    assert "layout" not in create("onnx", weights=str(fixed)).settings()
    with pytest.raises(ConfigError, match="is NCHW, but layout"):
        create("onnx", weights=str(fixed), layout="nhwc")
    with pytest.raises(ConfigError, match="choose nchw or nhwc"):
        create("onnx", weights=str(both), layout="chw")


def test_an_input_that_takes_other_than_3_channels_is_refused_when_loaded(tmp_path, capsys):
    model = graph_model(tmp_path / "grey.onnx", ["n", 1, 16, 32])
    code, err = match_error(tmp_path, capsys, model)
    assert code == 2 and "takes neither 3 channels first" in err and str(model) in err
    assert len(err.strip().splitlines()) == 1


def test_a_dynamic_channel_axis_warns_only_when_the_model_is_accepted(tmp_path, capsys):
    model = graph_model(tmp_path / "any.onnx", ["n", "c", "h", "w"])
    code, err = match_error(tmp_path, capsys, model)  # no input size: refused, one line, no warning before it
    assert code == 2 and "input size is not fixed" in err and len(err.strip().splitlines()) == 1
    code, err = match_error(tmp_path, capsys, model, "input_size=16x32")
    assert code == 0 and "warning: " in err and "layout=nhwc" in err


@pytest.mark.parametrize(
    "case, message",
    [
        ("uint8", "is tensor(uint8); fdnet gives a model float images"),
        ("two_inputs", "the model takes 2 inputs"),
        ("output_n_d_1", "a descriptor model returns (N, D) vectors"),
        ("output_d", "a descriptor model returns (N, D) vectors"),
        ("nan", "the model's output: the vector of image 0 of a batch of 3 holds NaN, infinity"),
        ("empty", "not an ONNX model onnxruntime can load"),
        ("truncated", "not an ONNX model onnxruntime can load"),
        ("directory", "ONNX model not found"),
    ],
)
def test_odd_models_are_one_line_naming_the_file(case, message, tmp_path, capsys):
    from onnx import TensorProto, helper, numpy_helper

    path = tmp_path / f"{case}.onnx"
    shape = ["n", 3, 16, 32]
    if case == "uint8":
        graph_model(path, shape, dtype="uint8")
    elif case == "two_inputs":
        import onnx

        graph_model(path, shape)
        model = onnx.load(str(path))
        model.graph.input.append(helper.make_tensor_value_info("mask", TensorProto.FLOAT, shape))
        onnx.save(model, str(path))
    elif case == "output_n_d_1":
        graph = graph_model(tmp_path / "base.onnx", shape)
        import onnx

        model = onnx.load(str(graph))
        model.graph.node.append(helper.make_node("Unsqueeze", ["v", "axis"], ["v3"]))
        model.graph.initializer.append(numpy_helper.from_array(np.array([2], np.int64), "axis"))
        del model.graph.output[:]
        model.graph.output.append(helper.make_tensor_value_info("v3", TensorProto.FLOAT, ["n", 4, 1]))
        onnx.save(model, str(path))
    elif case == "output_d":
        graph_model(
            path, shape, output_shape=[4], tail=[helper.make_node("ReduceMean", ["v"], ["v1"], axes=[0], keepdims=0)]
        )
    elif case == "nan":
        import onnx

        graph_model(
            path, shape, tail=[helper.make_node("Sub", ["v", "c"], ["vs"]), helper.make_node("Log", ["vs"], ["vn"])]
        )
        model = onnx.load(str(path))
        model.graph.initializer.append(numpy_helper.from_array(np.array(100, np.float32), "c"))
        onnx.save(model, str(path))
    elif case == "empty":
        path.write_bytes(b"")
    elif case == "truncated":
        path.write_bytes(graph_model(tmp_path / "whole.onnx", shape).read_bytes()[:100])
    elif case == "directory":
        path.mkdir()
    code, err = match_error(tmp_path, capsys, path)
    assert code == 2 and err.startswith("fdnet match: error: ") and message in err and str(path) in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "m.csv").exists()


def test_a_graph_fixed_at_batch_3_and_an_nhwc_graph_give_the_nchw_models_vectors(tmp_path):
    images = np.random.default_rng(3).random((7, 16, 32, 3), dtype=np.float32)
    expected = create("onnx", weights=str(graph_model(tmp_path / "n.onnx", ["n", 3, 16, 32]))).describe(images)
    three = create("onnx", weights=str(graph_model(tmp_path / "b3.onnx", [3, 3, 16, 32], output_shape=[3, 4])))
    assert three.batch_limit == 3
    np.testing.assert_allclose(three.describe(images), expected, atol=1e-6)  # 3 + 3 + 1 padded
    nhwc = create("onnx", weights=str(graph_model(tmp_path / "h.onnx", ["n", 16, 32, 3])))
    assert nhwc.layout == "nhwc"
    np.testing.assert_allclose(nhwc.describe(images), expected, atol=1e-6)


def test_an_unreadable_model_and_cuda_without_its_provider_are_one_line(tmp_path, capsys, monkeypatch):
    from pathlib import Path

    model = graph_model(tmp_path / "m.onnx", ["n", 3, 16, 32])
    if "CUDAExecutionProvider" not in onnxruntime.get_available_providers():
        images = write_random_places(tmp_path / "images", 3)
        assert (
            main(
                [
                    "match",
                    "--reference",
                    str(images),
                    "--query",
                    str(images),
                    "--method",
                    "onnx",
                    "--weights",
                    str(model),
                    "--device",
                    "cuda",
                    "--out",
                    str(tmp_path / "m.csv"),
                ]
            )
            == 2
        )
        err = capsys.readouterr().err
        assert "no CUDA provider" in err and len(err.strip().splitlines()) == 1

    def refuse(self):  # chmod 000 does not stop root: the read itself refuses
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "read_bytes", refuse)
    with pytest.raises(DataError, match="cannot read the ONNX model .Permission denied"):
        create("onnx", weights=str(model))


def test_an_all_zero_vector_is_an_error_not_a_silent_score_of_zero(tmp_path):
    class Zero(torch.nn.Module):
        def forward(self, x):
            return x.mean(dim=(2, 3)) * 0.0

    d = create("onnx", weights=str(export(Zero(), tmp_path / "zero.onnx")))
    assert d.dim == 3
    with pytest.raises(DataError, match="is all zero"):
        d.describe(np.random.default_rng(0).random((2, 16, 32, 3), dtype=np.float32))
    assert create("onnx", weights=str(tmp_path / "zero.onnx"), normalise="none").describe(
        np.ones((1, 16, 32, 3), np.float32)
    ).tolist() == [[0.0, 0.0, 0.0]]


def test_a_model_the_user_named_that_cannot_load_fails_the_benchmark(tmp_path, capsys):
    bad = tmp_path / "bad.onnx"
    bad.write_text("not a model")
    assert (
        main(
            [
                "benchmark",
                "--parts",
                "methods",
                "--method",
                "sad",
                "--weights",
                f"onnx:{bad}",
                "--quick",
                "--num-images",
                "2",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet benchmark: error: ") and str(bad) in err


def external_data_model(folder, seed):
    """``folder/m.onnx`` with every weight in ``folder/w.data``."""
    import onnx

    folder.mkdir(parents=True, exist_ok=True)
    export(MeanConv(seed=seed), folder / "whole.onnx")
    model = onnx.load(str(folder / "whole.onnx"))
    onnx.save_model(
        model,
        str(folder / "m.onnx"),
        save_as_external_data=True,
        all_tensors_to_one_file=True,
        location="w.data",
        size_threshold=0,
    )
    return folder / "m.onnx"


def test_external_weight_data_is_read_beside_the_model_and_fingerprinted(tmp_path, monkeypatch):
    a = external_data_model(tmp_path / "extA", seed=0)
    b = external_data_model(tmp_path / "extB", seed=1)
    assert a.read_bytes() == b.read_bytes()  # the same graph file: only w.data tells them apart
    images = np.random.default_rng(0).random((2, 16, 32, 3), dtype=np.float32)
    whole = create("onnx", weights=str(tmp_path / "extA" / "whole.onnx")).describe(images)
    monkeypatch.chdir(tmp_path / "extB")  # its w.data holds other weights
    from_b = create("onnx", weights="../extA/m.onnx")
    np.testing.assert_allclose(from_b.describe(images), whole, rtol=1e-5, atol=1e-6)
    monkeypatch.chdir(tmp_path)
    assert create("onnx", weights=str(a)).fingerprint() != create("onnx", weights=str(b)).fingerprint()


def test_external_data_outside_the_models_folder_is_refused_naming_the_model(tmp_path):
    import onnx

    model_path = external_data_model(tmp_path / "m", seed=0)
    model = onnx.load(str(model_path), load_external_data=False)
    for tensor in model.graph.initializer:
        for entry in tensor.external_data:
            if entry.key == "location":
                entry.value = "../w.data"
    (tmp_path / "w.data").write_bytes((tmp_path / "m" / "w.data").read_bytes())
    onnx.save_model(model, str(tmp_path / "m" / "escape.onnx"))
    with pytest.raises(DataError, match=r"escape\.onnx.*not a file inside the model's folder"):
        create("onnx", weights=str(tmp_path / "m" / "escape.onnx"))


@pytest.mark.parametrize("scale", [1e25, 1e-29])
def test_outputs_of_huge_or_tiny_values_keep_their_direction(scale, tmp_path):
    """Float32's sum of squares overflows at 1e25 (every vector became zero) and underflows at
    1e-29 (called all-zero): norms are taken in float64."""

    class Scaled(torch.nn.Module):
        def __init__(self, factor):
            super().__init__()
            self.conv, self.factor = MeanConv().conv, factor

        def forward(self, x):
            return self.conv(x).mean(dim=(2, 3)) * self.factor

    images = np.random.default_rng(0).random((3, 16, 32, 3), dtype=np.float32)
    plain = create("onnx", weights=str(export(Scaled(1.0), tmp_path / "plain.onnx"))).describe(images)
    scaled = create("onnx", weights=str(export(Scaled(scale), tmp_path / "scaled.onnx"))).describe(images)
    np.testing.assert_allclose(scaled, plain, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(scaled, axis=1), 1.0, rtol=1e-5)


def test_an_output_whose_length_varies_with_the_batch_is_one_line_naming_the_model(tmp_path, capsys):
    class BatchTiled(torch.nn.Module):
        def forward(self, x):
            return x.mean(dim=(2, 3)).repeat(1, x.shape[0])  # (N, 3N): the length follows the batch

    path = tmp_path / "tiled.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            BatchTiled(),
            (torch.rand(2, 3, 16, 32),),
            str(path),
            input_names=["images"],
            output_names=["vectors"],
            dynamic_axes={"images": {0: "n"}, "vectors": {0: "n", 1: "d"}},
            opset_version=17,
            dynamo=False,
        )
    d = create("onnx", weights=str(path))
    assert d.dim == 3
    with pytest.raises(
        DataError,
        match=r"tiled\.onnx: output vectors has shape \[4, 12\] for a batch of 4 images "
        r"but \(3,\) per image for one",
    ):
        d.describe(np.random.default_rng(0).random((4, 16, 32, 3), dtype=np.float32))
