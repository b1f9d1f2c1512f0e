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


@pytest.mark.parametrize("make_path", [
    lambda tmp: tmp / "file.txt" / "out.json",          # parent is a file
    lambda tmp: tmp,                                    # a directory where a file is expected
    lambda tmp: __import__("pathlib").Path("/proc/fdnet-cannot-write-here.json"),  # read-only fs
])
def test_ensure_writable_refuses_paths_that_cannot_be_written(tmp_path, make_path):
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable

    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(ConfigError, match="out|directory|cannot"):
        ensure_writable(make_path(tmp_path))
