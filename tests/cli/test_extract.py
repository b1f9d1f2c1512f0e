"""`fdnet extract`: the output path is checked before the model or any image is loaded."""

from fdnet.cli import main


def test_unwritable_out_fails_before_loading_the_model(tmp_path, capsys):
    images = tmp_path / "images"
    images.mkdir()
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    out = blocker / "vectors.npz"   # its parent is a regular file: nothing can be written there
    # the checkpoint does not exist either: the output is refused first, before any loading
    assert main(["extract", "--checkpoint", str(tmp_path / "no-run"), "--images", str(images),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet extract: error: ") and str(out) in err and "cannot create the vectors file" in err


def test_out_under_proc_is_refused(tmp_path, capsys):
    assert main(["extract", "--checkpoint", str(tmp_path / "no-run"), "--images", str(tmp_path),
                 "--out", "/proc/fdnet-extract-test/vectors.npz"]) == 2
    err = capsys.readouterr().err
    assert "/proc/fdnet-extract-test/vectors.npz" in err and "cannot create the vectors file" in err
