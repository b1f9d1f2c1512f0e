"""ONNX export of a (tiny) trained run gives the same vectors as the PyTorch descriptor."""

import numpy as np
import pytest

from fdnet.cli import main

onnxruntime = pytest.importorskip("onnxruntime", reason="optional extra fdnet[onnx] not installed")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    assert main(["synth", "--out", str(root / "route"), "--num-frames", "12", "--conditions", "summer,night"]) == 0
    assert (
        main(["train", "--data", str(root / "route"), "--preset", "tiny", "--out", str(root / "run"), "--no-progress"])
        == 0
    )
    return root / "run"


def test_export_matches_pytorch_descriptor(tiny_run, tmp_path, capsys):
    import fdnet

    out = tmp_path / "fdnet.onnx"
    assert main(["export", "--checkpoint", str(tiny_run), "--out", str(out)]) == 0
    assert "max abs difference" in capsys.readouterr().out
    model = fdnet.load(tiny_run)
    h, w = model.input_size
    images = np.random.default_rng(1).random((3, h, w, 3), dtype=np.float32)
    session = onnxruntime.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    onnx_vectors = session.run(["content"], {"images": images.transpose(0, 3, 1, 2).copy()})[0]
    np.testing.assert_allclose(onnx_vectors, model.describe(images), atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(onnx_vectors, axis=1), 1.0, atol=1e-5)


def test_export_of_missing_run_is_a_clear_error(tmp_path, capsys):
    assert main(["export", "--checkpoint", str(tmp_path / "nope"), "--out", str(tmp_path / "x.onnx")]) == 2
    assert "nope" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists()


def test_export_to_an_unwritable_path_fails_before_any_work(tiny_run, tmp_path, capsys, monkeypatch):
    import fdnet.methods.fdnet.descriptor as descriptor_module

    def must_not_load(*args, **kwargs):
        raise AssertionError("the model was loaded before the output path was checked")

    monkeypatch.setattr(descriptor_module.FDNetDescriptor, "from_run", must_not_load)
    (tmp_path / "file").write_text("x")
    assert main(["export", "--checkpoint", str(tiny_run), "--out", str(tmp_path / "file" / "x.onnx")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet export: error:") and "x.onnx" in err


def test_export_includes_the_backbone_trunk(tiny_run, tmp_path):
    """A run with model.backbone exports trunk + encoder as one graph, equal to PyTorch's vectors."""
    import fdnet

    run = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "--data",
                str(tiny_run.parent / "route"),
                "--preset",
                "tiny",
                "--out",
                str(run),
                "--no-progress",
                "--set",
                "model.backbone=efficientnet-lite0",
                "--set",
                "model.backbone_block=4",
                "--set",
                "model.input_size=[32,64]",
                "--set",
                "model.widths=[16]",
            ]
        )
        == 0
    )
    out = tmp_path / "trunk.onnx"
    assert main(["export", "--checkpoint", str(run), "--out", str(out)]) == 0
    images = np.random.default_rng(2).random((2, 32, 64, 3), dtype=np.float32)
    session = onnxruntime.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    onnx_vectors = session.run(["content"], {"images": images.transpose(0, 3, 1, 2).copy()})[0]
    np.testing.assert_allclose(onnx_vectors, fdnet.load(run).describe(images), atol=1e-4)


def test_projection_head_gives_its_length_to_extract_export_and_the_database(tiny_run, tmp_path, capsys):
    """model.content_head=trunk_projection: v_c is model.vector_length long (the cpu preset's 512,
    here 24) in fdnet extract, the ONNX graph and a place database, not the trunk map's length."""
    import json

    import fdnet

    route = tiny_run.parent / "route"
    run = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "--data",
                str(route),
                "--preset",
                "tiny",
                "--out",
                str(run),
                "--no-progress",
                "--set",
                "model.backbone=efficientnet-lite0",
                "--set",
                "model.backbone_block=4",
                "--set",
                "model.input_size=[32,64]",
                "--set",
                "model.widths=[16]",
                "--set",
                "model.content_head=trunk_projection",
                "--set",
                "model.vector_length=24",
                "--set",
                "model.projection_init=pca",
            ]
        )
        == 0
    )
    capsys.readouterr()
    images = route / "summer"
    vectors = tmp_path / "v.npz"
    assert main(["extract", "--checkpoint", str(run), "--images", str(images), "--out", str(vectors)]) == 0
    with np.load(vectors) as data:
        assert data["content"].shape == (12, 24)
    onnx_file = tmp_path / "p.onnx"
    assert main(["export", "--checkpoint", str(run), "--out", str(onnx_file)]) == 0
    sample = np.random.default_rng(3).random((2, 32, 64, 3), dtype=np.float32)
    session = onnxruntime.InferenceSession(str(onnx_file), providers=["CPUExecutionProvider"])
    onnx_vectors = session.run(["content"], {"images": sample.transpose(0, 3, 1, 2).copy()})[0]
    assert onnx_vectors.shape == (2, 24)
    np.testing.assert_allclose(onnx_vectors, fdnet.load(run).describe(sample), atol=1e-4)
    db = tmp_path / "map.db"
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(images),
                "--method",
                "fdnet",
                "--checkpoint",
                str(run),
                "--db",
                str(db),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert main(["database", "info", "--db", str(db)]) == 0
    assert json.loads(capsys.readouterr().out)["dim"] == 24
