"""`fdnet synth` and `fdnet demo`: outputs they cannot write and sizes they cannot render are
refused before any work, in one line (exit 2), with nothing left behind."""

from __future__ import annotations

import pytest

from fdnet.cli import main


@pytest.mark.parametrize(
    "size, message",
    [
        ("100000x100000", "size 100000x100000 is larger than any model here uses (at most 4096 pixels a side)"),
        ("4096x4096", "300 frames of 4096x4096 need about 151 GiB of memory to render a condition (at most 8 GiB)"),
    ],
)
def test_a_size_it_cannot_render_is_refused_before_allocating(tmp_path, capsys, size, message):
    assert main(["synth", "--out", str(tmp_path / "route"), "--size", size]) == 2
    assert f"fdnet synth: error: synthetic route: {message}" in capsys.readouterr().err
    assert not (tmp_path / "route").exists()


def test_synth_into_a_read_only_folder(tmp_path, capsys, make_read_only):
    make_read_only(tmp_path)
    assert main(["synth", "--out", str(tmp_path / "route"), "--num-frames", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fdnet synth: error: {tmp_path / 'route'}: cannot create the synthetic route folder: ")
    assert "Read-only file system" in err and "Traceback" not in err


@pytest.mark.parametrize("command", ["synth", "demo"])
def test_an_out_that_cannot_be_a_folder_is_one_line_on_any_machine(tmp_path, capsys, command):
    """A regular file, and a place no one may create anything (/proc), where no mount is allowed."""
    (tmp_path / "a-file").write_text("")
    for out, reason in (
        (tmp_path / "a-file", "exists and is not a folder"),
        ("/proc/fdnet-test/out", "cannot create the"),
    ):
        assert main([command, "--out", str(out), "--num-frames", "40"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"fdnet {command}: error: {out}") and reason in err and "Traceback" not in err
    assert (tmp_path / "a-file").read_text() == ""


def test_demo_into_a_read_only_folder(tmp_path, capsys, make_read_only):
    make_read_only(tmp_path)
    assert main(["demo", "--out", str(tmp_path / "demo")]) == 2
    printed = capsys.readouterr()
    assert printed.err.startswith(f"fdnet demo: error: {tmp_path / 'demo'}: cannot create the demo output folder")
    assert "Read-only file system" in printed.err and "=== 1/3" not in printed.out  # refused before step 1
