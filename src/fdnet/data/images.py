"""Reading images into float arrays, whatever their format.

Every image enters the pipeline as float32 RGB in [0, 1], shape (H, W, 3), resized to the size
the caller asks for; grey, RGBA, palette and 16-bit files are converted here so no descriptor
has to care. Errors name the file.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image, UnidentifiedImageError

from fdnet.errors import DataError

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")


def list_images(folder: str | os.PathLike) -> list[Path]:
    """Image files directly inside ``folder``, sorted by name (= traversal order)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: not a folder of images")
    paths = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if not paths:
        raise DataError(f"{folder}: contains no images (looked for {', '.join(IMAGE_EXTENSIONS)})")
    return paths


def _to_float_rgb(img: Image.Image, path: Path, source_mode: str | None = None) -> np.ndarray:
    mode = img.mode
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        # 16-bit (or 32-bit integer) grey: scale by the type's range, not by 255. ``source_mode``
        # is the file's own mode: a 16-bit image converted to "I" for resizing is still 16-bit,
        # even when it is so dark that no value exceeds 255.
        arr = np.asarray(img, dtype=np.float64)
        sixteen_bit = mode.startswith("I;16") or (source_mode or "").startswith("I;16")
        scale = 65535.0 if sixteen_bit or arr.max() > 255 else 255.0
        arr = np.clip(arr / scale, 0.0, 1.0).astype(np.float32)
        return np.repeat(arr[..., None], 3, axis=2)
    if mode == "F":
        arr = np.asarray(img, dtype=np.float32)
        hi = float(arr.max()) if arr.size else 1.0
        arr = arr / hi if hi > 1.0 else arr
        return np.repeat(np.clip(arr, 0, 1)[..., None], 3, axis=2)
    if mode in ("RGBA", "LA", "PA") or (mode == "P" and "transparency" in img.info):
        # Composite on black: transparent regions carry no scene content.
        img = img.convert("RGBA")
        background = Image.new("RGBA", img.size, (0, 0, 0, 255))
        img = Image.alpha_composite(background, img)
    return np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0


def load_image(path: str | os.PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read one image as float32 RGB in [0, 1], shape (H, W, 3).

    ``size`` is (height, width); when given the image is resized with area-averaging
    (Pillow's BOX filter when shrinking, bilinear when enlarging).
    """
    path = Path(path)
    try:
        with Image.open(path) as img:
            img.load()
            source_mode = img.mode
            if size is not None:
                height, width = int(size[0]), int(size[1])
                if height <= 0 or width <= 0:
                    raise DataError(f"{path}: requested image size {size} is not positive")
                shrinking = img.width >= width and img.height >= height
                if img.mode in ("I;16", "I;16B", "I;16L"):
                    img = img.convert("I")
                resample = Image.Resampling.BOX if shrinking else Image.Resampling.BILINEAR
                if (img.width, img.height) != (width, height):
                    if img.mode == "P":
                        img = img.convert("RGBA")
                    img = img.resize((width, height), resample)
            return _to_float_rgb(img, path, source_mode)
    except FileNotFoundError:
        raise DataError(f"{path}: image file not found") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise DataError(f"{path}: cannot read image ({exc.__class__.__name__}: {exc})") from None


def load_images(
    paths: Sequence[str | os.PathLike], size: tuple[int, int], workers: int = 2
) -> np.ndarray:
    """Read many images at one size into (N, H, W, 3) float32. Decoding runs in threads
    (Pillow releases the GIL while decoding)."""
    out = np.empty((len(paths), int(size[0]), int(size[1]), 3), dtype=np.float32)

    def read(i: int) -> None:
        out[i] = load_image(paths[i], size)

    if workers <= 1 or len(paths) < 8:
        for i in range(len(paths)):
            read(i)
    else:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            list(pool.map(read, range(len(paths))))
    return out


def to_grey(images: np.ndarray) -> np.ndarray:
    """(N, H, W, 3) RGB -> (N, H, W) luminance (ITU-R BT.601 weights, as OpenCV/Pillow use)."""
    return images[..., 0] * 0.299 + images[..., 1] * 0.587 + images[..., 2] * 0.114
