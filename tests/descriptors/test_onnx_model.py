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
        torch.onnx.export(module.eval(), (torch.rand(1, 3, *size),), str(path), input_names=["images"],
                          output_names=[output], dynamic_axes=axes, opset_version=17, dynamo=False)
    return path


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("onnx")
    assert main(["synth", "--out", str(root / "route"), "--num-frames", "12", "--conditions", "summer,night"]) == 0
    assert main(["train", "--data", str(root / "route"), "--preset", "tiny", "--out", str(root / "run"),
                 "--no-progress"]) == 0
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
        assert main(["extract", "--method", name, *options, "--images", str(images), "--out",
                     str(tmp_path / f"{name}.npz"), "--workers", "0"]) == 0
        with np.load(tmp_path / f"{name}.npz") as data:
            out[name] = data["descriptors" if name == "onnx" else "content"]
    assert out["onnx"].shape == out["fdnet"].shape == (200, fdnet.dim)
    np.testing.assert_allclose(out["onnx"], out["fdnet"], atol=1e-4)


def test_evaluate_gives_the_same_numbers_through_onnx_as_through_pytorch(tiny_run, tmp_path, capsys):
    run, model = tiny_run
    data = require_shared("gardens_point")
    common = ["evaluate", "--data", str(data), "--reference", "day_left", "--query", "night_right", "--frames",
              "100:140"]
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
        torch.onnx.export(MeanConv().eval(), (torch.rand(1, 3, 16, 32),), str(path), input_names=["images"],
                          output_names=["v"], opset_version=17, dynamo=False)
    d = create("onnx", weights=str(path))
    images = np.random.default_rng(1).random((5, 16, 32, 3), dtype=np.float32)
    one_by_one = np.concatenate([d.describe(images[i:i + 1]) for i in range(5)])
    np.testing.assert_allclose(d.describe(images), one_by_one, atol=1e-6)


@pytest.mark.parametrize("case, message", [
    ("not_onnx", "not an ONNX model onnxruntime can load"),
    ("four_d", "a descriptor model returns (N, D) vectors"),
    ("dynamic", "input size is not fixed"),
    ("missing", "ONNX model not found"),
])
def test_bad_models_are_one_line_errors(case, message, tmp_path, capsys):
    path = tmp_path / f"{case}.onnx"
    if case == "not_onnx":
        path.write_text("this is not a model\n")
    elif case == "four_d":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(torch.nn.Conv2d(3, 4, 3).eval(), (torch.rand(1, 3, 16, 32),), str(path),
                              input_names=["images"], output_names=["maps"], opset_version=17, dynamo=False)
    elif case == "dynamic":
        export(MeanConv(), path, dynamic_size=True)
    images = write_random_places(tmp_path / "images", 3)
    assert main(["match", "--reference", str(images), "--query", str(images), "--method", "onnx", "--weights",
                 str(path), "--out", str(tmp_path / "m.csv")]) == 2
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
    assert main(["database", "build", "--images", str(images), "--method", "onnx", "--weights", str(a), "--db",
                 str(db)]) == 0
    assert main(["database", "add", "--db", str(db), "--images", str(images), "--method", "onnx", "--weights",
                 str(b)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet database: error: ") and "Traceback" not in err

    route = tmp_path / "route"
    for condition, brightness in (("day", 1.0), ("dusk", 0.8)):
        write_random_places(route / condition, 12, seed=3, brightness=brightness)
    calibration = tmp_path / "cal.yaml"
    assert main(["calibrate", "--data", str(route), "--reference", "day", "--query", "dusk", "--method", "onnx",
                 "--weights", str(a), "--out", str(calibration)]) == 0
    capsys.readouterr()
    assert main(["match", "--reference", str(route / "day"), "--query", str(route / "dusk"), "--method", "onnx",
                 "--weights", str(b), "--calibration", str(calibration), "--out", str(tmp_path / "m.csv")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and str(calibration) in err and "Traceback" not in err
    assert main(["match", "--reference", str(route / "day"), "--query", str(route / "dusk"), "--method", "onnx",
                 "--weights", str(a), "--calibration", str(calibration), "--out", str(tmp_path / "m.csv")]) == 0
    assert "accepted" in read_csv_rows(tmp_path / "m.csv")[0]


def test_benchmark_times_an_onnx_model_beside_the_others(tmp_path, capsys):
    path = export(MeanConv(), tmp_path / "m.onnx")
    assert main(["benchmark", "--parts", "methods", "--method", "sad", "--weights", f"onnx={path}",
                 "--num-images", "4", "--quick", "--json", str(tmp_path / "b.json")]) == 0
    report = json.loads((tmp_path / "b.json").read_text())
    assert report["method_extraction_ms"]["onnx"] > 0 and report["ratio_vs_sad"]["onnx"] > 0
    assert "onnx" in capsys.readouterr().out
