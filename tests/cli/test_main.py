"""`fdnet` (cli/__init__.main): the one place where an operating-system error (a full disk, a
read-only folder, a permission, a file name that is not UTF-8) met by any command becomes
`fdnet COMMAND: error: ...` naming the path, exit code 2, with nothing half-written left behind.

Each command is run against a real full file system where the test may mount one (SmallDisk,
skipped otherwise) and, on any POSIX machine, under a file-size limit the kernel enforces
(file_size_limit: EFBIG instead of ENOSPC, the same path through the code)."""

from __future__ import annotations

import errno

import numpy as np
import pytest

from fdnet.cli import main


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    from fdnet.data.synthetic import generate_route

    root = tmp_path_factory.mktemp("route") / "route"
    generate_route(root, frames=30, conditions=["summer", "winter"], size=(32, 64))
    return root


@pytest.fixture(scope="module")
def vocabulary_images(tmp_path_factory):
    from fdnet.data.synthetic import generate_route

    root = tmp_path_factory.mktemp("orb") / "route"
    generate_route(root, frames=8, conditions=["summer"], size=(128, 256))
    return root / "summer"


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from tests.cli.test_extract import _tiny_run

    return _tiny_run(tmp_path_factory.mktemp("run") / "run")


def _commands(route, vocabulary_images, tiny_run, out):
    """command name -> argv writing into folder ``out``: each output is larger than 4 KiB."""
    summer, winter = str(route / "summer"), str(route / "winter")
    return {
        "database build": [
            "database",
            "build",
            "--images",
            summer,
            "--method",
            "sad",
            "--db",
            f"{out}/map.db",
            "--workers",
            "0",
        ],
        "match": [
            "match",
            "--reference",
            summer,
            "--query",
            winter,
            "--method",
            "sad",
            "--out",
            f"{out}/m.csv",
            "--workers",
            "0",
        ],
        "evaluate": [
            "evaluate",
            "--data",
            str(route),
            "--reference",
            "summer",
            "--query",
            "winter",
            "--method",
            "sad,hog",
            "--json",
            f"{out}/results.json",
            "--workers",
            "0",
        ],
        "groundtruth": [
            "groundtruth",
            "--aligned",
            "--num-queries",
            "500",
            "--num-references",
            "500",
            "--tolerance",
            "2",
            "--out",
            f"{out}/gt.csv",
        ],
        "vocabulary": [
            "vocabulary",
            "build",
            "--images",
            str(vocabulary_images),
            "--out",
            f"{out}/v.safetensors",
            "--size",
            "128",
            "256",
            "--branching",
            "8",
            "--depth",
            "3",
        ],
        "synth": ["synth", "--out", f"{out}/synthetic", "--num-frames", "10", "--size", "32x64"],
        "extract": [
            "extract",
            "--checkpoint",
            str(tiny_run),
            "--images",
            summer,
            "--out",
            f"{out}/v.npz",
            "--device",
            "cpu",
            "--workers",
            "0",
            "--fp32",
        ],
        "train": ["train", "--data", str(route), "--preset", "tiny", "--out", f"{out}/run", "--no-progress"],
    }


#: what a training that failed at its start keeps: its lock files (never deleted, see runs.RunLock)
#: and an empty log; no checkpoint, no configuration
#: what a training stopped by a failed write leaves: the run's lock, an empty log, and the save
#: locks of the checkpoints and of a stage's weights (no half generation)
RUN_LOCKS = {
    "run",
    "run/.lock",
    "run/log.csv",
    "run/checkpoints",
    "run/checkpoints/.save.lock",
    "run/stages",
    *(
        f"run/stages/{stage}{tail}"
        for stage in ("autoencoder", "critic", "joint")
        for tail in ("", "/checkpoints", "/checkpoints/.save.lock")
    ),
}
COMMANDS = ["database build", "match", "evaluate", "groundtruth", "vocabulary", "synth", "extract", "train"]


def _check_one_line(err: str, command: str, where: str, reasons: tuple[str, ...]) -> None:
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.startswith(f"fdnet {command.split()[0]}: error: ")]
    assert len(lines) == 1, err
    assert where in lines[0] and any(reason in lines[0] for reason in reasons), lines[0]


@pytest.mark.parametrize("command", COMMANDS)
def test_a_full_disk_is_one_line_naming_the_file_and_leaves_nothing(
    command, small_disk, route, vocabulary_images, tiny_run, capsys
):
    argv = _commands(route, vocabulary_images, tiny_run, small_disk.path)[command]
    small_disk.fill(4096)
    assert main(argv) == 2
    _check_one_line(capsys.readouterr().err, command, str(small_disk.path), ("no space left",))
    left = small_disk.files()
    if command == "train":
        assert set(left) <= RUN_LOCKS and (small_disk.path / "run/log.csv").stat().st_size == 0
    else:
        assert left == [], left


@pytest.mark.parametrize("command", COMMANDS)
def test_a_write_the_kernel_refuses_is_one_line_on_any_machine(
    command, tmp_path, route, vocabulary_images, tiny_run, file_size_limit, capsys
):
    argv = _commands(route, vocabulary_images, tiny_run, tmp_path / "out")[command]
    with file_size_limit(2048):
        code = main(argv)
    assert code == 2
    _check_one_line(capsys.readouterr().err, command, str(tmp_path / "out"), ("too large", "File too large"))
    left = sorted(str(p.relative_to(tmp_path / "out")) for p in (tmp_path / "out").rglob("*"))
    if command == "train":
        assert set(left) <= RUN_LOCKS
    else:
        assert left == [], left


@pytest.mark.parametrize(
    "error, expected",
    [
        (OSError(errno.ENOSPC, "No space left on device"), "writing OUT: no space left on the device"),
        (OSError(errno.ENOSPC, "No space left on device", "OUT/.part"), "OUT/.part: no space left on the device"),
        (PermissionError(errno.EACCES, "Permission denied", "/some/input.png"), "/some/input.png: permission denied"),
        (OSError(errno.EROFS, "Read-only file system", "/media/x"), "/media/x (writing OUT): read-only file system"),
        (
            UnicodeEncodeError("utf-8", "/maps/caf\udce9.png", 9, 10, "surrogates not allowed"),
            "a file name that is not valid UTF-8 ('/maps/caf\\udce9.png') cannot be written here; rename the file",
        ),
        (
            MemoryError("Unable to allocate 291. GiB"),
            "out of memory (Unable to allocate 291. GiB); use smaller inputs or settings",
        ),
    ],
)
def test_every_command_reports_an_os_error_as_one_line(error, expected, monkeypatch, capsys):
    import fdnet.cli.synth

    def fail(args):
        raise error

    monkeypatch.setattr(fdnet.cli.synth, "run", fail)
    assert main(["synth", "--out", "OUT"]) == 2
    assert capsys.readouterr().err == f"fdnet synth: error: {expected}\n"


@pytest.mark.parametrize(
    "error",
    [
        ValueError("a bug"),
        OSError(errno.EINVAL, "Invalid argument"),
        FileNotFoundError(errno.ENOENT, "No such file or directory"),
    ],
)
def test_a_bug_keeps_its_traceback(error, monkeypatch):
    import fdnet.cli.synth

    def fail(args):
        raise error

    monkeypatch.setattr(fdnet.cli.synth, "run", fail)
    with pytest.raises(type(error)):
        main(["synth", "--out", "OUT"])


def test_database_add_on_a_full_disk_is_one_line_and_keeps_the_database(small_disk, route, capsys):
    db = small_disk.path / "map.db"
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(route / "summer"),
                "--method",
                "sad",
                "--db",
                str(db),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    before = sorted(small_disk.files())
    small_disk.fill(4096)
    assert main(["database", "add", "--db", str(db), "--images", str(route / "winter"), "--workers", "0"]) == 2
    _check_one_line(capsys.readouterr().err, "database", str(small_disk.path), ("no space left",))
    # no spool left; SQLite's own -wal/-shm may stay (the next open uses or removes them)
    assert [f for f in small_disk.files() if not f.endswith(("-wal", "-shm"))] == before
    (small_disk.path / ".filler").unlink()
    assert main(["database", "info", "--db", str(db)]) == 0
    assert '"places": 30' in capsys.readouterr().out


def test_database_add_under_a_file_size_limit_is_one_line(tmp_path, route, file_size_limit, capsys):
    db = tmp_path / "out" / "map.db"
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(route / "summer"),
                "--method",
                "sad",
                "--db",
                str(db),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    before = sorted(p.name for p in db.parent.iterdir())
    with file_size_limit(2048):
        assert main(["database", "add", "--db", str(db), "--images", str(route / "winter"), "--workers", "0"]) == 2
    _check_one_line(capsys.readouterr().err, "database", str(db.parent), ("too large", "(ulimit -f)"))
    assert [p.name for p in sorted(db.parent.iterdir()) if not p.name.endswith(("-wal", "-shm"))] == before


def test_a_permission_error_without_a_path_keeps_its_traceback(monkeypatch):
    """Only a write's failure (a full disk) is told without a path; a pathless EPERM is no file's."""
    import fdnet.cli.synth

    def fail(args):
        raise PermissionError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(fdnet.cli.synth, "run", fail)
    with pytest.raises(PermissionError):
        main(["synth", "--out", "OUT"])


def test_short_quiet_and_an_unknown_flag_name_the_command(capsys):
    with pytest.raises(SystemExit) as stopped:
        main(["evaluate", "-q", "--nosuch", "1"])
    assert stopped.value.code == 2
    assert "fdnet evaluate: error: unrecognized arguments: --nosuch 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["database", "build", "--images", "x", "--db", "y.db", "--method", "raw", "--allow-duplicates"])
    assert "fdnet database build: error: unrecognized arguments: --allow-duplicates" in capsys.readouterr().err


def test_an_error_that_spans_lines_is_printed_as_one(capsys, monkeypatch):
    """A library's message can span lines (PyYAML's caret under a ROS 2 bag's metadata.yaml):
    the command's error is one line whatever its cause."""
    from fdnet.cli import evaluate
    from fdnet.errors import DataError

    def broken(args):
        raise DataError("bag/metadata.yaml: not valid YAML (while parsing\n  in 'x', line 1\n    ^\nexpected)")

    monkeypatch.setattr(evaluate, "run", broken)
    assert main(["evaluate", "--similarity", "x.npy", "--ground-truth", "g.csv"]) == 2
    err = capsys.readouterr().err
    assert err == "fdnet evaluate: error: bag/metadata.yaml: not valid YAML (while parsing in 'x', line 1 ^ expected)\n"


def test_a_refusal_keeps_its_cause_and_verbose_shows_the_traceback(tmp_path, capsys):
    """One line by default; with -v the traceback first, the cause chained (the parser's error that
    made the data error), then the same line."""
    bad = tmp_path / "gt.csv"
    bad.write_text("query_index,reference_indices\nx,1\n")
    np.save(tmp_path / "s.npy", np.eye(2))
    argv = ["evaluate", "--similarity", str(tmp_path / "s.npy"), "--ground-truth", str(bad)]
    assert main(argv) == 2
    quiet = capsys.readouterr().err
    assert quiet.startswith("fdnet evaluate: error: ") and quiet.count("\n") == 1 and "Traceback" not in quiet
    assert main([*argv, "-v"]) == 2
    loud = capsys.readouterr().err
    assert "Traceback" in loud and "ValueError" in loud and "direct cause of the following exception" in loud
    assert loud.rstrip("\n").splitlines()[-1] == quiet.rstrip("\n")


def test_a_value_that_starts_with_a_dash_is_explained(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["match", "--reference", str(tmp_path), "--query", str(tmp_path), "--method", "raw", "--out", "-x.csv"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("fdnet match: error: argument --out: expected one argument") and "--out=-x.csv" in err


@pytest.mark.parametrize(
    "case", ["match --out", "evaluate --json", "loop-closure --out", "match hard link", "match symlink"]
)
def test_an_output_that_is_one_of_the_commands_input_images_is_refused_and_the_image_kept(case, tmp_path, capsys):
    """Every image and video a command reads is protected from its outputs, under any name (a
    symbolic or a hard link too): one line naming both, the image byte for byte as it was."""
    import os
    import shutil

    from conftest import write_day_night_route

    route = write_day_night_route(tmp_path, 6)
    image = route / "night" / "003.png"
    before = image.read_bytes()
    target = image
    if case == "match hard link":
        target = tmp_path / "link.csv"
        os.link(image, target)
    elif case == "match symlink":
        target = tmp_path / "link.csv"
        target.symlink_to(image)
    command = case.split()[0]
    if command == "match":
        argv = [
            "match",
            "--reference",
            str(route / "day"),
            "--query",
            str(route / "night"),
            "--method",
            "raw",
            "--out",
            str(target),
        ]
    elif command == "evaluate":
        argv = [
            "evaluate",
            "--data",
            str(route),
            "--reference",
            "day",
            "--query",
            "night",
            "--method",
            "raw",
            "--json",
            str(target),
        ]
    else:
        shutil.copytree(route / "night", tmp_path / "loop")
        image = target = tmp_path / "loop" / "003.png"
        argv = [
            "loop-closure",
            "--images",
            str(tmp_path / "loop"),
            "--method",
            "raw",
            "--exclude-last",
            "2",
            "--threshold",
            "0.5",
            "--out",
            str(image),
        ]
    code = main([*argv, "--workers", "0"])
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert code == 2 and len(errors) == 1 and "Traceback" not in err, err
    assert errors[0].startswith(f"fdnet {command}: error: {target}: ")
    assert f"the input image {image} the command reads" in errors[0]
    assert image.read_bytes() == before


def test_output_to_a_reader_that_left_ends_quietly(tmp_path):
    """`fdnet ... | head -c 10`: the reader closes the pipe; the command ends without a traceback,
    with the shell's code for SIGPIPE, as Unix tools do. The read end is closed before the command
    starts, so its first write meets the closed pipe."""
    import os
    import subprocess
    import sys

    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        result = subprocess.run(
            [sys.executable, "-m", "fdnet", "methods"], stdout=write_end, stderr=subprocess.PIPE, text=True, timeout=120
        )
    finally:
        os.close(write_end)
    assert result.returncode == 141 and result.stderr == "", result.stderr
