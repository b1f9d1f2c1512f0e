"""What an image list is, by content: the one rule every check of "was this computed from these
images?" uses (a saved index's map, the processes of one torchrun extraction, precomputed vectors).

An image is identified by its absolute path as listed and the size and modification time (in
nanoseconds) of the file behind it: a frame of a video or bag by that file's. Base names alone
are never enough: conditions of one route share them (``summer/frame_00010.png``,
``winter/frame_00010.png``), and a rewritten image keeps its name.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Sequence


def image_facts(path: str | os.PathLike) -> tuple[str, int, int] | None:
    """(absolute path as listed, size, modification time in ns) of an image, of the video or bag
    file behind a frame; None when it cannot be read."""
    from fdnet.data.frame_records import locate

    path = Path(path)
    found = None if path.is_file() else locate(path)
    backing = found[0] if found is not None else path
    try:
        stat = backing.stat()
    except OSError:
        return None
    return os.path.abspath(path), int(stat.st_size), int(stat.st_mtime_ns)


def describe_facts(facts: tuple[str, int, int] | None) -> str:
    return "unreadable" if facts is None else f"{facts[0]} ({facts[1]} bytes, modified {facts[2]} ns)"


def images_digest(paths: Sequence[str | os.PathLike]) -> str:
    """SHA-256 over :func:`image_facts` of every image, in order."""
    digest = hashlib.sha256()
    for path in paths:
        facts = image_facts(path)
        text = "unreadable" if facts is None else f"{facts[1]}\0{facts[2]}"
        digest.update(os.fsencode(os.path.abspath(path)) + b"\0" + text.encode() + b"\n")
    return digest.hexdigest()
