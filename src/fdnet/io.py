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
import tempfile
from pathlib import Path
from typing import Iterator

from fdnet.errors import ConfigError


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


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is synced and renamed over ``path``.

    The rename is atomic on POSIX when both live in the same directory, so readers see either
    the old file or the complete new one. On failure (an exception, a full disk) the temporary
    file is removed and ``path`` is untouched.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp creates 0600; give the result the permissions a plain open() would (umask).
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)
        fsync_file(tmp_path)
        os.replace(tmp_path, target)
        fsync_directory(target.parent)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def ensure_writable(path: str | os.PathLike, what: str = "output", directory: bool = False) -> Path:
    """Check, before any work starts, that ``path`` can be written; raise ConfigError if not.

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
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        where = "" if directory else f" (its folder {folder})"
        raise ConfigError(f"{target}: cannot create the {what} folder{where}: {exc.strerror or exc}") from None
    try:
        fd, probe = tempfile.mkstemp(prefix=".fdnet-write-test.", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        reason = "no space left" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
        raise ConfigError(f"{target}: cannot write the {what} here ({reason})") from None
    return target
