import os
import stat

import pytest

from fdnet.io import atomic_path, atomic_write_text


def test_atomic_write_replaces_whole_file_with_normal_permissions(tmp_path):
    target = tmp_path / "sub" / "out.txt"
    atomic_write_text(target, "one")
    atomic_write_text(target, "two")
    assert target.read_text() == "two"
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~umask
    assert [p.name for p in target.parent.iterdir()] == ["out.txt"]


def test_failed_write_leaves_previous_file_and_no_temporary(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash mid-write")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_ensure_writable_accepts_new_file_in_new_folder(tmp_path):
    from fdnet.io import ensure_writable

    ensure_writable(tmp_path / "a" / "b" / "out.json")
    assert (tmp_path / "a" / "b").is_dir()
    assert list((tmp_path / "a" / "b").iterdir()) == []  # the probe file is gone


@pytest.mark.parametrize(
    "make_path",
    [
        lambda tmp: tmp / "file.txt" / "out.json",  # parent is a file
        lambda tmp: tmp,  # a directory where a file is expected
        lambda tmp: __import__("pathlib").Path("/proc/fdnet-cannot-write-here.json"),  # read-only fs
    ],
)
def test_ensure_writable_refuses_paths_that_cannot_be_written(tmp_path, make_path):
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable

    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(ConfigError, match="out|directory|cannot"):
        ensure_writable(make_path(tmp_path))


def test_a_full_disk_mid_write_is_one_clear_error_and_keeps_the_old_file(tmp_path, monkeypatch):
    import errno
    from pathlib import Path

    from fdnet.errors import ConfigError

    target = tmp_path / "out.yaml"
    target.write_text("old")

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full)
    with pytest.raises(ConfigError, match="out.yaml: cannot write it \\(no space left") as caught:
        atomic_write_text(target, "new")
    assert isinstance(caught.value, OSError)  # code that tolerates a failed cache write still does
    monkeypatch.undo()
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.yaml"]


def test_a_full_disk_found_before_the_work_is_an_output_error(tmp_path, monkeypatch):
    import errno

    from fdnet import io
    from fdnet.errors import OutputError

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io.os, "write", full)
    with pytest.raises(OutputError, match="out.json: cannot write the output here \\(no space left\\)") as caught:
        io.ensure_writable(tmp_path / "out.json")
    assert caught.value.errno == errno.ENOSPC and isinstance(caught.value, OSError)


def test_an_input_error_inside_the_block_is_not_called_an_output_error(tmp_path):
    from fdnet.errors import OutputError

    with pytest.raises(FileNotFoundError) as caught:
        with atomic_path(tmp_path / "out.txt"):
            open(tmp_path / "missing-input.txt").read()
    assert not isinstance(caught.value, OutputError)


def test_a_device_or_pipe_is_refused_as_an_output_file(tmp_path):
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable

    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    with pytest.raises(ConfigError, match="device, pipe or socket"):
        ensure_writable(pipe)
    with pytest.raises(ConfigError, match="device, pipe or socket"):
        atomic_write_text(pipe, "x")
    assert stat.S_ISFIFO(pipe.stat().st_mode)  # not replaced by a regular file


def test_text_naming_a_non_utf8_file_is_written_with_the_files_own_bytes(tmp_path):
    name = os.fsdecode(b"caf\xe9 =odd.png")  # Latin-1 bytes, as a file system may hold them
    target = tmp_path / "matches.csv"
    atomic_write_text(target, f"query\n{name}\n")
    assert target.read_bytes() == b"query\ncaf\xe9 =odd.png\n"


@pytest.mark.parametrize(
    "name, cell",
    [
        ("=1+2.png", "'=1+2.png"),
        ("+a.png", "'+a.png"),
        ("-a.png", "'-a.png"),
        ("@a.png", "'@a.png"),
        ("\ta.png", "'\ta.png"),
        ("\ra.png", "'\ra.png"),
        ("'a.png", "''a.png"),
        ("a=b.png", "a=b.png"),
        ("frame_0001.png", "frame_0001.png"),
        ("", ""),
    ],
)
def test_spreadsheet_text_quotes_formula_starts_and_reads_back(name, cell):
    from fdnet.io import from_spreadsheet_text, spreadsheet_text

    assert spreadsheet_text(name) == cell
    assert from_spreadsheet_text(cell) == name


def test_no_output_is_written_over_a_noted_input_under_any_name(tmp_path):
    """The one guard of outputs against inputs: the input itself, a symbolic link and a hard link
    to it are refused by the atomic writer and by the check made before any work."""
    import os

    from fdnet.errors import ConfigError
    from fdnet.io import atomic_write_text, ensure_writable, forget_inputs, note_inputs

    image = tmp_path / "frame.png"
    image.write_bytes(b"\x89PNG pixels")
    (tmp_path / "soft.csv").symlink_to(image)
    os.link(image, tmp_path / "hard.csv")
    note_inputs([image])
    try:
        for name in ("frame.png", "soft.csv", "hard.csv"):
            with pytest.raises(ConfigError, match=rf"{name}: this output is the input image {image} the command reads"):
                atomic_write_text(tmp_path / name, "csv")
            with pytest.raises(ConfigError, match="the command reads"):
                ensure_writable(tmp_path / name)
        atomic_write_text(tmp_path / "other.csv", "csv")  # anything else is written
    finally:
        forget_inputs()
    assert image.read_bytes() == b"\x89PNG pixels"


def test_a_replaced_output_keeps_its_permissions(tmp_path):
    from fdnet.io import output_mode

    private = tmp_path / "private.csv"
    private.write_text("old")
    os.chmod(private, 0o600)
    atomic_write_text(private, "new")
    assert private.read_text() == "new" and stat.S_IMODE(private.stat().st_mode) == 0o600
    shared = tmp_path / "shared.csv"
    shared.write_text("old")
    os.chmod(shared, 0o664)
    atomic_write_text(shared, "new")
    assert stat.S_IMODE(shared.stat().st_mode) == 0o664
    assert output_mode(tmp_path / "new.csv") == stat.S_IMODE(0o666 & ~_umask())


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask
