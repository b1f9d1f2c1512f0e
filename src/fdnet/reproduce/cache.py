"""Descriptor cache: the vectors one model gave one list of images, kept on disk.

A set of vectors is stored under a key hashed from everything that made it: the method, its
settings, the fingerprint of its weights (:meth:`~fdnet.descriptors.base.Descriptor.fingerprint`),
what a learning method was fitted on, which vectors (content or appearance), and the image list
(each file's absolute path, size and modification time, in order). A rerun with one more method
therefore describes only that method, and a run interrupted after some sets resumes from them.
Each set is written atomically, so an interruption never leaves half a file under a valid key.

Layout: ``FOLDER/<key>.npy`` (float32) and ``FOLDER/<key>.json`` (the key's parts, for people).

Size: the folder is kept under a cap (:data:`DEFAULT_MAX_BYTES`, or ``$FDNET_CACHE_MAX_MB``
mebibytes; 0 for no cap): after each set is stored, the sets used longest ago (a hit counts as a
use) are removed until the folder fits, never one this process used. Removing the folder by hand
is always safe: what is missing is described again.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from fdnet.io import atomic_path, atomic_write_text

#: bump when the meaning of a cached array changes, so old entries are never read as new ones
CACHE_VERSION = 1


def image_list_key(paths: Sequence[str | os.PathLike]) -> str:
    """sha256 of an ordered image list: absolute path, size and mtime of every file. A renamed,
    reordered, added or rewritten image gives another key."""
    digest = hashlib.sha256()
    for path in paths:
        path = Path(path).resolve()
        stat = path.stat()
        digest.update(f"{path}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return digest.hexdigest()


class DescriptorCache:
    """``vectors(parts, compute)``: the stored array for ``parts``, or ``compute()`` stored.

    ``hits`` and ``computed`` count what happened (``computed`` lists the ``label`` of each set
    described), so a caller can say what a run reused.
    """

    def __init__(self, folder: str | os.PathLike, max_bytes: int | None = None) -> None:
        self.folder = Path(folder)
        self.hits = 0
        self.computed: list[str] = []
        self.max_bytes = cache_cap() if max_bytes is None else int(max_bytes)
        #: sets this process loaded or stored: never removed to make room
        self._used: set[Path] = set()

    def key(self, parts: dict) -> str:
        text = json.dumps({"cache_version": CACHE_VERSION, **parts}, sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()

    def path(self, parts: dict) -> Path:
        return self.folder / f"{self.key(parts)}.npy"

    def load(self, parts: dict) -> np.ndarray | None:
        path = self.path(parts)
        if not path.is_file():
            return None
        try:
            cached = np.load(path, allow_pickle=False)
        except (OSError, ValueError):
            return None  # unreadable (e.g. a disk error): described again and rewritten
        if not np.issubdtype(cached.dtype, np.number) or not np.isfinite(cached).all():
            # a damaged or hand-edited cache file would surface later as "scores contain NaN" with no
            # file named: say which one, and describe again
            logging.getLogger(__name__).warning(
                f"{path}: cached vectors hold NaN or infinite values; describing " "the images again"
            )
            return None
        return cached

    def vectors(self, parts: dict, compute: Callable[[], np.ndarray], label: str = "") -> np.ndarray:
        cached = self.load(parts)
        if cached is not None:
            self.hits += 1
            self._mark_used(self.path(parts))
            return cached
        vectors = np.ascontiguousarray(compute(), dtype=np.float32)
        path = self.path(parts)
        with atomic_path(path) as tmp, open(tmp, "wb") as handle:
            np.save(handle, vectors, allow_pickle=False)
        atomic_write_text(
            path.with_suffix(".json"),
            json.dumps({"label": label, "shape": list(vectors.shape), **parts}, indent=1, sort_keys=True, default=str)
            + "\n",
        )
        self.computed.append(label)
        self._mark_used(path)
        self._keep_under_cap()
        return vectors

    def _mark_used(self, path: Path) -> None:
        self._used.add(path)
        try:
            os.utime(path)  # the time of last use orders what goes first
        except OSError:
            pass

    def _keep_under_cap(self) -> None:
        """Remove the sets used longest ago until the folder fits :attr:`max_bytes`."""
        if self.max_bytes <= 0:
            return
        sets = []
        for path in self.folder.glob("*.npy"):
            try:
                info = path.stat()
            except OSError:
                continue
            sets.append((info.st_mtime_ns, path, info.st_size))
        total = sum(size for _, _, size in sets)
        for _, path, size in sorted(sets):
            if total <= self.max_bytes:
                break
            if path in self._used:
                continue
            for file in (path, path.with_suffix(".json")):
                with contextlib.suppress(OSError):
                    file.unlink()
            total -= size
            logging.getLogger(__name__).debug(
                "%s: removed from the descriptor cache to keep it under %d bytes", path, self.max_bytes
            )


#: the descriptor cache's default size cap (bytes); ``$FDNET_CACHE_MAX_MB`` sets another
DEFAULT_MAX_BYTES = 4 << 30


def cache_cap() -> int:
    """The cache's size cap in bytes: ``$FDNET_CACHE_MAX_MB`` (0: no cap), else
    :data:`DEFAULT_MAX_BYTES`; a value that is not a whole number is a ConfigError."""
    from fdnet.errors import ConfigError

    text = os.environ.get("FDNET_CACHE_MAX_MB", "").strip()
    if not text:
        return DEFAULT_MAX_BYTES
    try:
        megabytes = int(text)
    except ValueError as exc:
        raise ConfigError(f"FDNET_CACHE_MAX_MB={text!r}: give a whole number of mebibytes (0 for no cap)") from exc
    if megabytes < 0:
        raise ConfigError(f"FDNET_CACHE_MAX_MB={text!r}: give a whole number of mebibytes (0 for no cap)")
    return megabytes << 20
