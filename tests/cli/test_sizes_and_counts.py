"""One check per kind of number: image sizes no model uses and thread counts out of range are the
command's one-line error before anything is allocated or described; a size such as 0x0 is a
size, not YAML's hexadecimal 0."""

import pytest

from fdnet.cli import main
from fdnet.data.images import MAX_IMAGE_SIDE, check_image_size
from fdnet.errors import ConfigError


def test_the_one_image_size_check():
    assert check_image_size((32, 64), "x") == (32, 64) and check_image_size(["8", 8.0], "x") == (8, 8)
    for bad, message in (((0, 5), "must be positive"), ((MAX_IMAGE_SIDE + 1, 5), "larger than any model"),
                         ((10**20, 64), "larger than any model"), ((2.5, 4), "two whole numbers"),
                         ((True, 4), "two whole numbers"), ((3,), "two whole numbers"), ("3x4", "two whole")):
        with pytest.raises(ConfigError, match=message):
            check_image_size(bad, "x")


@pytest.mark.parametrize("argv, message", [
    (["choose-trunk", "--data", "d", "--reference", "a", "--query", "b", "--input-size", "100000", "100000",
      "--out", "c.yaml"], "--input-size: size 100000x100000 is larger than any model here uses"),
    (["choose-trunk", "--data", "d", "--reference", "a", "--query", "b", "--input-size", "99999999999999999999",
      "64", "--out", "c.yaml"], "is larger than any model here uses"),
    (["extract", "--method", "raw", "--method-set", "size=0x0", "--images", "d", "--out", "x.npz"],
     "raw: size 0x0 must be positive"),
    (["extract", "--method", "trunk", "--method-set", "input_size=[9000,9000]", "--images", "d", "--out", "x.npz"],
     "trunk: input_size: size 9000x9000 is larger than any model here uses"),
])
def test_sizes_no_model_uses_are_refused_first(tmp_path, monkeypatch, capsys, argv, message):
    from conftest import write_random_places

    monkeypatch.chdir(tmp_path)
    write_random_places(tmp_path / "d", 2)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("argv", [
    ["extract", "--method", "raw", "--images", "d", "--out", "x.npz", "--threads", "-1"],
    ["choose-trunk", "--data", "d", "--reference", "a", "--query", "b", "--out", "c.yaml", "--threads", "0"],
    ["evaluate", "--data", "d", "--method", "raw", "--threads", "99999999999999999999"],
    ["train", "--data", "d", "--threads", "-3"],
    ["benchmark", "--threads", "x"],
    ["reproduce", "--threads", "2000"],
])
def test_thread_counts_out_of_range_are_the_commands_error(argv, capsys):
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert f"fdnet {argv[0]}: error: argument --threads: must be" in err and "Traceback" not in err
