"""Tiny fixture folders in the published layouts (a few small images with the real file names)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image


def write_image(path: Path, size=(8, 6), value: int = 0, mode: str = "RGB") -> Path:
    """A small image whose pixels all equal ``value`` (size is width x height)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    channels = {"RGB": 3, "L": 1}[mode]
    arr = np.full((size[1], size[0], channels), value % 256, dtype=np.uint8)
    Image.fromarray(arr[..., 0] if channels == 1 else arr, mode).save(path)
    return path


def write_frames(folder: Path, names, size=(8, 6)) -> list[Path]:
    return [write_image(folder / name, size, value=i * 7) for i, name in enumerate(names)]
