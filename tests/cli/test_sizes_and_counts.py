"""One check per kind of number: image sizes no model uses and thread counts out of range are the
command's one-line error before anything is allocated or described; a size such as 0x0 is a
size, not YAML's hexadecimal 0."""

import pytest

from fdnet.cli import main
from fdnet.data.images import MAX_IMAGE_SIDE, check_image_size
from fdnet.errors import ConfigError


def test_the_one_image_size_check():
    assert check_image_size((32, 64), "x") == (32, 64) and check_image_size(["8", 8.0], "x") == (8, 8)
    for bad, message in (
        ((0, 5), "must be positive"),
        ((MAX_IMAGE_SIDE + 1, 5), "larger than any model"),
        ((10**20, 64), "larger than any model"),
        ((2.5, 4), "two whole numbers"),
        ((True, 4), "two whole numbers"),
        ((3,), "two whole numbers"),
        ("3x4", "two whole"),
    ):
        with pytest.raises(ConfigError, match=message):
            check_image_size(bad, "x")


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            [
                "choose-trunk",
                "--data",
                "d",
                "--reference",
                "a",
                "--query",
                "b",
                "--input-size",
                "100000",
                "100000",
                "--out",
                "c.yaml",
            ],
            "--input-size: size 100000x100000 is larger than any model here uses",
        ),
        (
            [
                "choose-trunk",
                "--data",
                "d",
                "--reference",
                "a",
                "--query",
                "b",
                "--input-size",
                "99999999999999999999",
                "64",
                "--out",
                "c.yaml",
            ],
            "is larger than any model here uses",
        ),
        (
            ["extract", "--method", "raw", "--method-set", "size=0x0", "--images", "d", "--out", "x.npz"],
            "raw: size 0x0 must be positive",
        ),
        (
            [
                "extract",
                "--method",
                "trunk",
                "--method-set",
                "input_size=[9000,9000]",
                "--images",
                "d",
                "--out",
                "x.npz",
            ],
            "trunk: input_size: size 9000x9000 is larger than any model here uses",
        ),
    ],
)
def test_sizes_no_model_uses_are_refused_first(tmp_path, monkeypatch, capsys, argv, message):
    from conftest import write_random_places

    monkeypatch.chdir(tmp_path)
    write_random_places(tmp_path / "d", 2)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "argv",
    [
        ["extract", "--method", "raw", "--images", "d", "--out", "x.npz", "--threads", "-1"],
        ["choose-trunk", "--data", "d", "--reference", "a", "--query", "b", "--out", "c.yaml", "--threads", "0"],
        ["evaluate", "--data", "d", "--method", "raw", "--threads", "99999999999999999999"],
        ["train", "--data", "d", "--threads", "-3"],
        ["benchmark", "--threads", "x"],
        ["reproduce", "--threads", "2000"],
    ],
)
def test_thread_counts_out_of_range_are_the_commands_error(argv, capsys):
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert f"fdnet {argv[0]}: error: argument --threads: must be" in err and "Traceback" not in err


@pytest.mark.parametrize(
    "setting, message",
    [
        ("orientations=0", "HOG bins 0 must be a whole number from 1 to 360"),
        ("orientations=-1", "HOG bins -1 must be a whole number from 1 to 360"),
        ("block_size=0", "HOG block size 0x0 must be between 1 and 4096"),
        ("cell_size=0", "HOG cell size 0x0 must be between 1 and 4096"),
        ("cell_size=5", "must be a multiple of the cell 5x5"),
    ],
)
def test_hog_settings_that_crash_opencv_are_refused(tmp_path, capsys, setting, message):
    """Each of these crashed the interpreter inside cv2.HOGDescriptor (SIGSEGV, SIGFPE, a
    ZeroDivisionError or an exabyte allocation); one check refuses them for every HOG built."""
    from conftest import write_random_places

    write_random_places(tmp_path / "d", 2)
    assert (
        main(
            [
                "extract",
                "--method",
                "hog",
                "--method-set",
                setting,
                "--images",
                str(tmp_path / "d"),
                "--out",
                str(tmp_path / "x.npz"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert message in err and err.startswith("fdnet extract: error: hog: ")


@pytest.mark.parametrize(
    "setting, message",
    [
        ("model.hog.nbins=0", "calc: model.hog: HOG bins 0"),
        ("model.hog.nbins=-1", "calc: model.hog: HOG bins -1"),
        ("model.hog.cell_size=[0,0]", "calc: model.hog: HOG cell size 0x0"),
        ("model.input_size=[1,1]", "does not fit the 1x1 input"),
    ],
)
def test_calc_settings_that_crash_are_refused(tmp_path, capsys, setting, message):
    from conftest import write_day_night_set

    data = write_day_night_set(tmp_path / "data")
    assert (
        main(
            ["train", "calc", "--data", str(data), "--preset", "tiny", "--set", setting, "--out", str(tmp_path / "run")]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
