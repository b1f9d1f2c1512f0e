"""`fdnet vocabulary build`."""

from __future__ import annotations

from fdnet.cli import main
from fdnet.descriptors.dbow import DBoWDescriptor

from conftest import require_shared


def test_build_writes_a_loadable_vocabulary(tmp_path, capsys):
    root = require_shared("gardens_point")
    out = tmp_path / "voc.safetensors"
    code = main(
        [
            "vocabulary",
            "build",
            "--images",
            str(root / "day_left"),
            str(root / "night_right"),
            "--out",
            str(out),
            "--max-images",
            "6",
            "--depth",
            "2",
            "--size",
            "144",
            "256",
        ]
    )
    assert code == 0
    assert "words" in capsys.readouterr().out
    d = DBoWDescriptor(vocabulary=out, input_size=(144, 256))
    assert 2 <= d.dim <= 100
    assert d.vocabulary.info["training_images"] == 6


def test_missing_folder_is_a_clear_error(tmp_path, capsys):
    code = main(["vocabulary", "build", "--images", str(tmp_path / "nope"), "--out", str(tmp_path / "v")])
    assert code == 2
    err = capsys.readouterr().err
    assert "nope" in err and "Traceback" not in err
    assert not (tmp_path / "v").exists()


def test_an_out_that_is_a_folder_is_refused_before_the_orb_work(tmp_path, capsys, monkeypatch):
    import fdnet.descriptors.dbow as dbow
    from fdnet.data.synthetic import generate_route

    def learn(*args, **kwargs):
        raise AssertionError("the ORB work started before --out was checked")

    monkeypatch.setattr(dbow, "learn_vocabulary", learn)
    images = generate_route(tmp_path / "route", frames=2, conditions=["summer"], size=(32, 64)).root / "summer"
    (tmp_path / "folder").mkdir()
    assert main(["vocabulary", "build", "--images", str(images), "--out", str(tmp_path / "folder")]) == 2
    err = capsys.readouterr().err
    assert f"fdnet vocabulary: error: {tmp_path / 'folder'}: vocabulary file path is a directory" in err
