"""`fdnet extract`: the output path is checked before the model or any image is loaded."""

from fdnet.cli import main


def test_unwritable_out_fails_before_loading_the_model(tmp_path, capsys):
    images = tmp_path / "images"
    images.mkdir()
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    out = blocker / "vectors.npz"  # its parent is a regular file: nothing can be written there
    # the checkpoint does not exist either: the output is refused first, before any loading
    assert main(["extract", "--checkpoint", str(tmp_path / "no-run"), "--images", str(images), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet extract: error: ") and str(out) in err and "cannot create the vectors file" in err


def test_out_under_proc_is_refused(tmp_path, capsys):
    assert (
        main(
            [
                "extract",
                "--checkpoint",
                str(tmp_path / "no-run"),
                "--images",
                str(tmp_path),
                "--out",
                "/proc/fdnet-extract-test/vectors.npz",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "/proc/fdnet-extract-test/vectors.npz" in err and "cannot create the vectors file" in err


def _tiny_run(path):
    import torch

    from fdnet.methods.fdnet.config import preset
    from fdnet.methods.fdnet.model import FDNet
    from fdnet.runs import save_checkpoint

    config = preset("tiny")
    torch.manual_seed(0)
    save_checkpoint(path, FDNet(config.model).named_parts(), config, state={"step": 1})
    return path


def _images(folder, n):
    import numpy as np
    from PIL import Image

    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):  # natural order: frame_2 before frame_10
        Image.fromarray(rng.integers(0, 256, size=(20 + i % 3, 40, 3), dtype=np.uint8)).save(folder / f"frame_{i}.png")
    return folder


def test_extract_streams_batches_into_the_npz(tmp_path, capsys):
    import numpy as np

    from fdnet.data.images import list_images, load_images
    from fdnet.descriptors import create

    run = _tiny_run(tmp_path / "run")
    images = _images(tmp_path / "images", 37)
    out = tmp_path / "v.npz"
    assert (
        main(
            [
                "extract",
                "--checkpoint",
                str(run),
                "--images",
                str(images),
                "--out",
                str(out),
                "--fp32",
                "--batch-size",
                "8",
                "--workers",
                "1",
                "--device",
                "cpu",
            ]
        )
        == 0
    )
    assert "37 images" in capsys.readouterr().out
    d = create("fdnet", checkpoint=run, device="cpu")
    paths = list_images(images)
    loaded = load_images(paths, d.input_size)
    with np.load(out, allow_pickle=False) as z:
        assert list(z["names"]) == [p.name for p in paths] and z["names"][2] == "frame_2.png"
        np.testing.assert_allclose(z["content"], d.describe(loaded), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(z["appearance"], d.describe_appearance(loaded), rtol=1e-5, atol=1e-5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "run", "v.npz"]  # no parts left


def test_extract_stops_at_an_unreadable_image_and_leaves_nothing(tmp_path, capsys):
    run = _tiny_run(tmp_path / "run")
    images = _images(tmp_path / "images", 20)
    (images / "frame_13.png").write_bytes(b"broken")
    out = tmp_path / "v.npz"
    assert (
        main(
            [
                "extract",
                "--checkpoint",
                str(run),
                "--images",
                str(images),
                "--out",
                str(out),
                "--batch-size",
                "4",
                "--workers",
                "1",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet extract: error: ") and "frame_13.png" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "run"]


def test_extract_works_for_every_kind_of_method(tmp_path, capsys):
    """A numpy method, a method that learns from images (here from the images it describes) and
    a trained baseline: each writes ``descriptors`` equal to its own ``describe``."""
    import json

    import numpy as np
    import torch

    from fdnet.data.images import list_images, load_images
    from fdnet.descriptors import create
    from fdnet.methods.calc import model as calc
    from fdnet.methods.calc.config import tiny_config
    from fdnet.runs import save_checkpoint

    images = _images(tmp_path / "images", 12)
    calc_run = tmp_path / "calc-run"
    torch.manual_seed(0)
    save_checkpoint(calc_run, {"calc": calc.build_network(tiny_config().model)}, tiny_config(), state={"step": 1})
    paths = list_images(images)
    for method, extra, fitted in (
        ("sad", [], False),
        ("trunk-whitened", ["--method-set", "dim=4"], True),
        ("calc", ["--checkpoint", str(calc_run)], False),
    ):
        out = tmp_path / f"{method}.npz"
        assert (
            main(
                [
                    "extract",
                    "--method",
                    method,
                    *extra,
                    "--images",
                    str(images),
                    "--out",
                    str(out),
                    "--fp32",
                    "--workers",
                    "0",
                    "--device",
                    "cpu",
                    "--no-progress",
                ]
            )
            == 0
        )
        printed = capsys.readouterr().out
        assert f"12 images -> {out} ({method}: descriptors" in printed
        assert ("learnt from the 12 extracted images" in printed) == fitted
        options = (
            {"checkpoint": str(calc_run), "bf16": False}
            if method == "calc"
            else {"dim": 4, "bf16": False}
            if fitted
            else {}
        )
        d = create(method, device="cpu", **options)
        if fitted:
            d.fit(paths)
        with np.load(out, allow_pickle=False) as z:
            assert set(z.files) == {
                "descriptors",
                "names",
                "sources",
                "timestamps",
                "sizes",
                "mtimes_ns",
                "method",
                "fingerprint",
                "settings",
            }
            assert str(z["method"]) == method and isinstance(json.loads(str(z["settings"])), dict)
            np.testing.assert_allclose(
                z["descriptors"], d.describe(load_images(paths, d.input_size)), rtol=1e-4, atol=1e-5
            )


def test_extract_names_one_method(tmp_path, capsys):
    assert (
        main(
            [
                "extract",
                "--method",
                "sad,hog",
                "--images",
                str(_images(tmp_path / "i", 2)),
                "--out",
                str(tmp_path / "v.npz"),
            ]
        )
        == 2
    )
    assert "name one" in capsys.readouterr().err


def test_a_runs_recorded_method_is_used_or_named(tmp_path, capsys):
    """`extract --checkpoint CALC_RUN` describes with CALC (the run records its method); naming
    another trained method for it is refused with the method to give."""
    from conftest import write_day_night_set

    data = write_day_night_set(tmp_path / "data")
    run = tmp_path / "calc"
    assert main(["train", "calc", "--data", str(data), "--preset", "tiny", "--steps", "2", "--out", str(run)]) == 0
    capsys.readouterr()
    assert (
        main(["extract", "--checkpoint", str(run), "--images", str(data / "day"), "--out", str(tmp_path / "v.npz")])
        == 0
    )
    printed = capsys.readouterr().out
    # float32 by default, as every other command describes (bf16 only with --bf16)
    assert "(calc: descriptors" in printed and ", fp32," in printed
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(data),
                "--reference",
                "day",
                "--query",
                "night",
                "--method",
                "fdnet",
                "--checkpoint",
                str(run),
            ]
        )
        == 2
    )
    assert f"{run}: a run of `fdnet train calc`, not of fdnet: give --method calc" in capsys.readouterr().err
    # a method that reads an FDNet run's trunk names the run's method too, not the run config's keys
    assert (
        main(
            [
                "extract",
                "--method",
                "trunk",
                "--checkpoint",
                str(run),
                "--images",
                str(data / "day"),
                "--out",
                str(tmp_path / "t.npz"),
            ]
        )
        == 2
    )
    assert (
        f"{run}: a run of `fdnet train calc`, but --method trunk takes a run of `fdnet train fdnet`: give "
        "--method calc for this run"
    ) in capsys.readouterr().err


def test_extract_h5_holds_the_npz_vectors_as_hlocs_global_features(tmp_path, capsys):
    """`--format h5`: the place descriptor (FDNet's content) per image, named relative to --images
    (hloc's image_dir), equal to the .npz extract's; streamed in batches, nothing left beside it."""
    import numpy as np

    from fdnet.descriptors.hloc_formats import read_global_features

    run = _tiny_run(tmp_path / "run")
    images = _images(tmp_path / "images", 13)
    common = [
        "--checkpoint",
        str(run),
        "--images",
        str(images),
        "--fp32",
        "--batch-size",
        "4",
        "--workers",
        "1",
        "--device",
        "cpu",
        "--no-progress",
    ]
    assert main(["extract", *common, "--out", str(tmp_path / "v.npz")]) == 0
    assert main(["extract", *common, "--format", "h5", "--out", str(tmp_path / "v.h5")]) == 0
    printed = capsys.readouterr().out
    assert f"13 images -> {tmp_path / 'v.h5'} (fdnet: content as hloc's global_descriptor" in printed
    assert f"relative to {images} (hloc's image_dir)" in printed
    names, vectors = read_global_features(tmp_path / "v.h5")
    with np.load(tmp_path / "v.npz", allow_pickle=False) as z:
        npz_names, content = [str(n) for n in z["names"]], z["content"]
    assert sorted(names) == sorted(npz_names) and "frame_2.png" in names
    order = [npz_names.index(n) for n in names]
    np.testing.assert_array_equal(vectors, content[order])
    assert vectors.dtype == np.float32
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "run", "v.h5", "v.npz"]


def test_extract_format_follows_the_suffix_and_a_mismatch_is_refused(tmp_path, capsys):
    from fdnet.descriptors.hloc_formats import read_global_features

    images = _images(tmp_path / "images", 3)
    common = ["--method", "sad", "--images", str(images), "--workers", "0", "--no-progress"]
    assert main(["extract", *common, "--out", str(tmp_path / "v.hdf5")]) == 0  # h5, from the suffix
    assert read_global_features(tmp_path / "v.hdf5")[0] == ["frame_0.png", "frame_1.png", "frame_2.png"]
    assert main(["extract", *common, "--format", "h5", "--out", str(tmp_path / "w")]) == 0
    assert (tmp_path / "w.h5").is_file()
    capsys.readouterr()
    for given, out in (("h5", "x.npz"), ("npz", "x.h5")):
        assert main(["extract", *common, "--format", given, "--out", str(tmp_path / out)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"fdnet extract: error: --format {given} --out {tmp_path / out}: the file name says")
        assert err.count("\n") == 1 and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "v.hdf5", "w.h5"]


def test_extract_h5_stops_at_an_unreadable_image_and_leaves_nothing(tmp_path, capsys):
    images = _images(tmp_path / "images", 9)
    (images / "frame_6.png").write_bytes(b"broken")
    out = tmp_path / "v.h5"
    out.write_bytes(b"the old file")
    assert (
        main(
            [
                "extract",
                "--method",
                "sad",
                "--images",
                str(images),
                "--format",
                "h5",
                "--out",
                str(out),
                "--batch-size",
                "2",
                "--workers",
                "1",
                "--no-progress",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet extract: error: ") and "frame_6.png" in err and err.count("\n") == 1
    assert out.read_bytes() == b"the old file"  # untouched, and no temporary beside it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "v.h5"]


def test_extract_h5_names_a_videos_frames_relative_to_its_folder(tmp_path, capsys):
    import numpy as np

    from fdnet.descriptors.hloc_formats import read_global_features
    from tests.data.source_files import write_video

    frames = np.random.default_rng(0).integers(0, 256, size=(3, 16, 24, 3), dtype=np.uint8)
    (tmp_path / "route").mkdir()
    video = write_video(tmp_path / "route" / "summer.avi", frames)
    out = tmp_path / "v.h5"
    assert (
        main(
            ["extract", "--method", "sad", "--images", str(video), "--out", str(out), "--workers", "0", "--no-progress"]
        )
        == 0
    )
    names, _ = read_global_features(out)
    assert len(names) == 3 and all(n.startswith("summer.avi/frame_") for n in names)
    assert f"relative to {tmp_path / 'route'}" in capsys.readouterr().out


def test_extract_recursive_h5_names_images_as_hlocs_image_dir_does(tmp_path):
    """hloc's image_dir holds db/ and query/: --recursive names its images db/0001.png, ... as
    hloc's extract_features does, so pairs_from_retrieval's db_prefix and query_prefix work."""
    import h5py

    from fdnet.descriptors.hloc_formats import read_global_features

    root = tmp_path / "images"
    root.mkdir()
    _images(root / "db", 3)
    _images(root / "query", 2)
    (root / "query" / ".hidden").mkdir()
    (root / "query" / ".hidden" / "x.png").write_bytes((root / "query" / "frame_0.png").read_bytes())
    out = tmp_path / "global-feats.h5"
    assert (
        main(
            [
                "extract",
                "--method",
                "sad",
                "--images",
                str(root),
                "--recursive",
                "--out",
                str(out),
                "--workers",
                "0",
                "--no-progress",
            ]
        )
        == 0
    )
    names, vectors = read_global_features(out)
    assert names == ["db/frame_0.png", "db/frame_1.png", "db/frame_2.png", "query/frame_0.png", "query/frame_1.png"]
    with h5py.File(out, "r") as f:  # what hloc's get_descriptors reads
        assert f["query/frame_1.png"]["global_descriptor"][()].tobytes() == vectors[4].tobytes()


def test_torchrun_two_processes_write_the_npz_one_process_writes(tmp_path):
    """`torchrun --nproc-per-node 2 -m fdnet extract`: each process describes half the images,
    rank 0 writes the file: names, sources and timestamps exactly, vectors within 1e-5 of one
    process's, settings the same but for world_size; nothing left beside it or in TMPDIR."""
    import json

    import numpy as np

    from tests.descriptors.test_sharding import spools, torchrun

    run = _tiny_run(tmp_path / "run")
    images = _images(tmp_path / "images", 23)
    common = [
        "extract",
        "--checkpoint",
        str(run),
        "--images",
        str(images),
        "--fp32",
        "--batch-size",
        "4",
        "--workers",
        "0",
        "--device",
        "cpu",
        "--no-progress",
    ]
    assert main([*common, "--out", str(tmp_path / "one.npz")]) == 0
    result = torchrun(*common, "--out", tmp_path / "two.npz", tmpdir=tmp_path / "tmp")
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("fdnet extract: 23 images ->") == 1 and "2 processes, cpu" in result.stdout
    with np.load(tmp_path / "one.npz", allow_pickle=False) as one, np.load(tmp_path / "two.npz") as two:
        assert set(one.files) == set(two.files)
        for name in ("names", "sources", "method"):
            np.testing.assert_array_equal(two[name], one[name])
        np.testing.assert_array_equal(two["timestamps"], one["timestamps"])  # NaN for image files, in both
        for name in ("content", "appearance"):
            np.testing.assert_allclose(two[name], one[name], rtol=0, atol=1e-5)
        settings_one, settings_two = json.loads(str(one["settings"])), json.loads(str(two["settings"]))
    assert settings_one.pop("world_size") == 1 and settings_two.pop("world_size") == 2
    assert settings_one == settings_two
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "one.npz", "run", "tmp", "two.npz"]
    assert spools(tmp_path / "tmp") == []


def test_torchrun_a_killed_process_stops_the_other_and_a_rerun_writes_the_whole_file(tmp_path):
    """Process 1 killed (SIGKILL) after 2 of its 4 batches: process 0 stops with one error line
    and leaves no output and no parts; the killed one's spool stays in its TMPDIR until the next
    run there removes it; that run writes the whole file, as one process does."""
    import numpy as np

    from fdnet.descriptors.sharding import KILL_VARIABLE
    from tests.descriptors.test_sharding import error_lines, spools, torchrun

    images = _images(tmp_path / "images", 30)
    out = tmp_path / "v.npz"
    common = [
        "extract",
        "--method",
        "sad",
        "--images",
        str(images),
        "--out",
        str(out),
        "--batch-size",
        "4",
        "--workers",
        "0",
        "--no-progress",
    ]
    killed = torchrun(*common, tmpdir=tmp_path / "tmp", env={KILL_VARIABLE: "1:2"})
    assert killed.returncode != 0
    errors = error_lines(killed)
    assert len(errors) == 1, killed.stderr
    assert "process 0 of 2 lost contact" in errors[0] or "stopped by SIGTERM" in errors[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "tmp"]  # no output, no parts
    assert len(spools(tmp_path / "tmp")) == 1  # the killed process's
    again = torchrun(*common, tmpdir=tmp_path / "tmp")
    assert again.returncode == 0, again.stderr
    assert spools(tmp_path / "tmp") == []
    assert main([*common[:5], "--out", str(tmp_path / "one.npz"), *common[7:]]) == 0
    with np.load(out) as two, np.load(tmp_path / "one.npz") as one:
        assert len(two["names"]) == 30
        np.testing.assert_array_equal(two["names"], one["names"])
        np.testing.assert_allclose(two["descriptors"], one["descriptors"], rtol=0, atol=1e-5)


def test_a_checkpoint_rotted_on_disk_is_refused_naming_the_file(tmp_path, capsys):
    run = _tiny_run(tmp_path / "run")
    weights = next(run.rglob("model.safetensors"))
    data = bytearray(weights.read_bytes())
    data[-4096 - 64 : -64] = b"\xff" * 4096  # inside the tensor data: safetensors itself reads it without a word
    weights.write_bytes(bytes(data))
    out = tmp_path / "v.npz"
    code = main(
        [
            "extract",
            "--checkpoint",
            str(run),
            "--images",
            str(_images(tmp_path / "images", 3)),
            "--out",
            str(out),
            "--workers",
            "0",
            "--device",
            "cpu",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and f"{weights}: the weights do not match the checksum" in err, err
    assert len(err.strip().splitlines()) == 1 and not out.exists()


def test_extract_refuses_vectors_that_are_not_finite_naming_the_first_image(tmp_path, capsys):
    import torch

    from fdnet.methods.fdnet.config import preset
    from fdnet.methods.fdnet.model import FDNet
    from fdnet.runs import save_checkpoint

    config = preset("tiny")
    model = FDNet(config.model)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.fill_(float("nan"))  # saved so, checksum and all: the vectors are NaN
    save_checkpoint(tmp_path / "run", model.named_parts(), config, state={"step": 1})
    images = _images(tmp_path / "images", 3)
    out = tmp_path / "v.npz"
    code = main(
        [
            "extract",
            "--checkpoint",
            str(tmp_path / "run"),
            "--images",
            str(images),
            "--out",
            str(out),
            "--workers",
            "0",
            "--device",
            "cpu",
            "--fp32",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and f"the vector of {images / 'frame_0.png'} holds NaN" in err, err
    assert len(err.strip().splitlines()) == 1 and not out.exists()


def test_replacing_a_private_vectors_file_keeps_it_private(tmp_path):
    import os
    import stat

    images = _images(tmp_path / "images", 3)
    for name in ("v.npz", "v.h5"):
        out = tmp_path / name
        out.write_bytes(b"old")
        os.chmod(out, 0o600)
        assert (
            main(
                [
                    "extract",
                    "--method",
                    "sad",
                    "--images",
                    str(images),
                    "--out",
                    str(out),
                    "--workers",
                    "0",
                    "--no-progress",
                ]
            )
            == 0
        )
        assert out.stat().st_size > 3 and stat.S_IMODE(out.stat().st_mode) == 0o600, name
