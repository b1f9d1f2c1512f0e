"""Descriptor cache: the vectors one model gave one list of images, kept on disk.

A set of vectors is stored under a key hashed from everything that made it: the method, its
settings, the fingerprint of its weights (:meth:`~fdnet.descriptors.base.Descriptor.fingerprint`),
what a learning method was fitted on, which vectors (content or appearance), and the image list
(each file's absolute path, size and modification time, in order). A rerun with one more method
therefore describes only that method, and a run interrupted after some sets resumes from them.
Each set is written atomically, so an interruption never leaves half a file under a valid key.

Layout: ``FOLDER/<key>.npy`` (float32) and ``FOLDER/<key>.json`` (the key's parts, for people).
"""

from __future__ import annotations

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

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.hits = 0
        self.computed: list[str] = []

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
            logging.getLogger(__name__).warning(f"{path}: cached vectors hold NaN or infinite values; describing "
                                                "the images again")
            return None
        return cached

    def vectors(self, parts: dict, compute: Callable[[], np.ndarray], label: str = "") -> np.ndarray:
        cached = self.load(parts)
        if cached is not None:
            self.hits += 1
            return cached
        vectors = np.ascontiguousarray(compute(), dtype=np.float32)
        path = self.path(parts)
        with atomic_path(path) as tmp, open(tmp, "wb") as handle:
            np.save(handle, vectors, allow_pickle=False)
        atomic_write_text(path.with_suffix(".json"), json.dumps(
            {"label": label, "shape": list(vectors.shape), **parts}, indent=1, sort_keys=True, default=str) + "\n")
        self.computed.append(label)
        return vectors
