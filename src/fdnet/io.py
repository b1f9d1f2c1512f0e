"""Atomic, durable file output: a crash, kill -9 or Ctrl-C never leaves a half-written result.

Every output goes to a temporary file beside its target, is flushed to disk (``fsync``), then
renamed over the target; the directory is synced too, so after a power cut the rename is not
lost either. :func:`ensure_writable` lets a command refuse an output path it cannot write
*before* it spends minutes on the work.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from pathlib import Path
from typing import Iterator

from fdnet.errors import ConfigError, OutputError, output_error


def fsync_directory(folder: str | os.PathLike) -> None:
    """Make a rename or a new entry in ``folder`` durable (a no-op where directories cannot be
    opened, e.g. on Windows)."""
    try:
        fd = os.open(str(folder), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def fsync_file(path: str | os.PathLike) -> None:
    fd = os.open(str(path), os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


#: every file this process's command reads (images, videos, bags), as the lists the command holds
#: anyway (no copy) and what they are; :func:`refuse_writing_an_input` keeps outputs off them
_INPUTS: list[tuple[object, str]] = []


def note_inputs(paths, what: str = "input image") -> None:
    """Record files the command reads, so no output is ever written over one
    (:func:`refuse_writing_an_input`). ``paths`` is kept as it is, not copied: give the list the
    command itself holds. A frame of a video or bag stands for its file."""
    _INPUTS.append((paths, what))


def forget_inputs() -> None:
    """Start a new command: what earlier commands in this process read is no longer protected."""
    _INPUTS.clear()


def refuse_writing_an_input(target: str | os.PathLike, what: str = "output") -> None:
    """The one guard of outputs against inputs: ConfigError when ``target`` is a file the command
    reads (:func:`note_inputs`) under any name: the same path, a symbolic link to it or a hard
    link (compared by device and inode). Writing it would destroy what the command reads."""
    if not _INPUTS:
        return
    try:
        own = os.stat(target)
    except OSError:
        return  # nothing there yet: no input to destroy
    if not stat.S_ISREG(own.st_mode):
        return
    for paths, kind in list(_INPUTS):
        for name in paths:
            name = os.fspath(name)
            try:
                theirs = os.stat(_backing_file(name))
            except OSError:
                continue
            if (theirs.st_dev, theirs.st_ino) == (own.st_dev, own.st_ino):
                raise ConfigError(
                    f"{target}: this {what} is the {kind} {name} the command reads; writing it "
                    "would destroy it: give another name"
                )


def _backing_file(name: str) -> str:
    """The file behind an input name: itself, or the video or bag a frame path lies in."""
    path = Path(name)
    if not path.exists():
        for parent in path.parents:
            if parent.is_file():
                return str(parent)
    return name


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is synced and renamed over ``path``.

    The rename is atomic on POSIX when both live in the same directory, so readers see either
    the old file or the complete new one. On failure (an exception, a full disk) the temporary
    file is removed and ``path`` is untouched.
    """
    target = Path(path)
    _refuse_special_file(target, "output")
    refuse_writing_an_input(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    except OSError as exc:
        raise _output_error(target, exc) from exc
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
            os.chmod(tmp_path, output_mode(target))  # mkstemp creates 0600
            fsync_file(tmp_path)
            os.replace(tmp_path, target)
        except OutputError:
            raise
        except OSError as exc:  # a full disk mid-write: one clear line, the old file kept
            if exc.errno in _WRITE_ERRNOS or exc.filename in (None, str(tmp_path), str(target)):
                raise _output_error(target, exc) from exc
            raise  # e.g. an input the caller reads inside the block: not this output's fault
        fsync_directory(target.parent)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def output_mode(target: str | os.PathLike) -> int:
    """The one file-mode rule of outputs: a file that replaces another keeps the replaced file's
    permissions (a 0600 CSV stays 0600); a new one gets what a plain open() would give (0666
    less the umask)."""
    try:
        return stat.S_IMODE(os.stat(target).st_mode)
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


#: errors that are always about the file being written
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG})


def _output_error(target: Path, exc: OSError) -> OutputError:
    reason = "no space left on the device" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
    return output_error(f"{target}: cannot write it ({reason}); nothing was written there", exc)


def _refuse_special_file(target: Path, what: str) -> None:
    """An existing device, pipe or socket is no output file: the atomic rename would replace it."""
    if target.exists() and not target.is_file() and not target.is_dir():
        raise ConfigError(f"{target}: {what} path is a device, pipe or socket, not a file; give a file name")


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """UTF-8; a file name that is not UTF-8 (decoded by Python with surrogate escapes) is written
    back as its own bytes, so a CSV names the very file instead of failing after the work."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8", errors="surrogateescape")


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def ensure_writable(path: str | os.PathLike, what: str = "output", directory: bool = False) -> Path:
    """Check, before any work starts, that ``path`` can be written; raise ConfigError if not
    (:class:`~fdnet.errors.OutputError`, also an OSError, when the operating system refuses).

    For a file: its folder (created if missing) must accept a new file, and an existing ``path``
    must not be a directory. ``directory=True``: ``path`` is a folder the command writes into.
    A probe file is created and removed, because permission bits alone do not tell (read-only
    mounts, root in a container, ACLs).
    """
    target = Path(path)
    folder = target if directory else target.parent
    if not directory and target.is_dir():
        raise ConfigError(f"{target}: {what} path is a directory, expected a file name")
    if directory and target.exists() and not target.is_dir():
        raise ConfigError(f"{target}: {what} folder exists and is not a folder")
    if not directory:
        _refuse_special_file(target, what)
        refuse_writing_an_input(target, what)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        where = "" if directory else f" (its folder {folder})"
        raise output_error(f"{target}: cannot create the {what} folder{where}: {exc.strerror or exc}", exc) from exc
    try:
        fd, probe = tempfile.mkstemp(prefix=".fdnet-write-test.", dir=folder)
        try:
            os.write(fd, b"x")  # an empty file needs no space: a full disk only shows on a write
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        reason = "no space left" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
        raise output_error(f"{target}: cannot write the {what} here ({reason})", exc) from exc
    return target


def private_folder(path: str | os.PathLike, what: str = "temporary folder") -> Path:
    """A folder under a shared directory (``/tmp``) that only this user can use: created with
    mode 0700; an existing one is refused when it is a symbolic link, is not a folder, belongs to
    another user or is writable by others (whoever made it could read or replace the files put
    there), and made 0700 when it is merely readable by others."""
    folder = Path(path)
    try:
        os.mkdir(folder, 0o700)
    except FileExistsError:
        pass
    except OSError as exc:
        raise output_error(f"{folder}: cannot create the {what} ({exc.strerror or exc})", exc) from exc
    info = os.lstat(folder)
    if stat.S_ISLNK(info.st_mode):
        raise ConfigError(
            f"{folder}: the {what} is a symbolic link (to {os.readlink(folder)}); refused, since "
            "its files would go wherever it points: remove it"
        )
    if not stat.S_ISDIR(info.st_mode):
        raise ConfigError(f"{folder}: the {what} exists and is not a folder; remove it")
    if hasattr(os, "getuid") and info.st_uid != os.getuid():
        raise ConfigError(
            f"{folder}: the {what} belongs to another user (uid {info.st_uid}); refused: remove it "
            "or set TMPDIR to a folder of your own"
        )
    if info.st_mode & 0o022:
        raise ConfigError(
            f"{folder}: the {what} is writable by other users (mode {stat.S_IMODE(info.st_mode):o}); "
            "refused: remove it or set TMPDIR to a folder of your own"
        )
    if info.st_mode & 0o077:
        os.chmod(folder, 0o700)
    return folder


#: first characters that make a spreadsheet read a CSV cell as a formula (OWASP, "CSV injection"),
#: plus the quote itself, so that the escape can be undone exactly
_SPREADSHEET_TRIGGERS = ("=", "+", "-", "@", "\t", "\r", "'")


def spreadsheet_text(name: str) -> str:
    """A text cell (an image name) for a CSV that no spreadsheet evaluates: a name starting with
    ``= + - @``, a tab or a carriage return gets a leading single quote (the OWASP advice), and so
    does one starting with a quote, so :func:`from_spreadsheet_text` gives back the very name.
    Numbers are written as they are."""
    name = str(name)
    return "'" + name if name.startswith(_SPREADSHEET_TRIGGERS) else name


def from_spreadsheet_text(cell: str) -> str:
    """The name :func:`spreadsheet_text` wrote as ``cell``."""
    return cell[1:] if cell.startswith("'") and cell[1:].startswith(_SPREADSHEET_TRIGGERS) else cell


def markdown_cell(text) -> str:
    """Text for one cell of a Markdown table: a ``|`` (which would start another column), a
    backslash and the characters that would format it are escaped; line breaks become spaces."""
    import re

    return re.sub(r"([\\|*_`])", r"\\\1", " ".join(str(text).split()))
