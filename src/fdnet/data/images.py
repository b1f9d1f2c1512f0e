"""Reading images into float arrays, whatever their format, and the one order of a folder's images.

Every image enters the pipeline as float32 RGB in [0, 1], shape (H, W, 3), resized to the size
the caller asks for; grey, RGBA, palette and 16-bit files are converted here so no descriptor
has to care. Errors name the file.

**Image order.** :func:`list_images` is the only place a condition's images are listed, and
:func:`natural_key` the only order: every command, dataset adapter and ground-truth file uses
it, so index ``i`` means the same image everywhere (see ``docs/datasets.md``, "Image order").
"""

from __future__ import annotations

import os
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image, UnidentifiedImageError

from fdnet.errors import DataError

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")

# ASCII digits only: ``\d`` would also match other scripts' digits, and ``str.isdigit`` accepts
# superscripts that int() rejects; published datasets number frames with 0-9.
_DIGIT_RUNS = re.compile(r"([0-9]+)")


def image_name(path: str | os.PathLike) -> str:
    """An image's name in every output that names images of a run (``fdnet match``'s and
    ``database query``'s CSVs, ``evaluate --predictions``, loop-closure events, a place database's
    places): its absolute path as listed. Absolute, so outputs made from different working
    directories join on it; not resolved, so a symbolic link keeps its own name (two links to one
    file are two images, in the folder's order). A video's or bag's frame is named by its frame
    path (``SOURCE/FRAME``, :mod:`fdnet.data.sources`). A ground-truth CSV, which belongs to a
    dataset rather than a run, names images by file name within its folders; every output also
    carries the image's index, on which it joins with the ground truth."""
    return os.path.abspath(os.fspath(path))


def natural_key(name: str | os.PathLike) -> tuple:
    """Sort key of the natural order: ``frame_2`` before ``frame_10``.

    Runs of digits compare as numbers, everything else case-sensitively as text (``B`` before
    ``a``, as plain sorting does). Names that differ only in leading zeros (``frame_01``,
    ``frame_1``) compare equal as numbers, so the plain name breaks the tie: the order is total
    and does not depend on the order the file system lists files in.
    """
    name = os.fspath(name)
    # split() alternates text and digit runs and always starts with text (possibly ""), so the
    # i-th elements of two keys have the same type and tuples compare without a TypeError.
    parts = _DIGIT_RUNS.split(name)
    return tuple(int(part) if i % 2 else part for i, part in enumerate(parts)), name


def _is_hidden(relative: Path) -> bool:
    # ".DS_Store", macOS "._frame.png" resource forks, ".thumbnails/": never images of the route
    return any(part.startswith(".") for part in relative.parts)


def list_images(folder: str | os.PathLike, recursive: bool = False) -> list[Path]:
    """The image files of one condition, in traversal order: the natural order of their names.

    Image files are those with an extension in :data:`IMAGE_EXTENSIONS` (any case); hidden files
    (and, with ``recursive``, files under hidden folders) are left out. Names are compared with
    :func:`natural_key`: digit runs as numbers, the rest case-sensitively as text, ties (names that
    differ only in leading zeros) broken by the plain name. So ``frame_1.png, frame_2.png, ...,
    frame_10.png`` come in that order, and zero-padded names come in plain text order.
    ``recursive=True`` lists the whole tree, ordered by the path below ``folder``
    (``a/2.png`` before ``a/10.png`` before ``b/1.png``). A video file or ROS bag (``BAG:TOPIC``)
    in place of the folder gives its frames as frame paths, sampled by the default
    :class:`fdnet.data.sources.SourceOptions` (:func:`fdnet.data.sources.list_frames`).

    Index ``i`` of this list is image ``i`` everywhere in fdnet: in ground-truth CSVs, similarity
    matrices, ``fdnet match`` output and ``fdnet extract`` arrays.
    """
    from fdnet.data import sources
    from fdnet.io import note_inputs

    if sources.is_source(folder):  # a video or ROS bag: its frames, as frame paths (fdnet.data.sources)
        frames = sources.list_frames(folder)
        note_inputs([sources.split_topic(folder)[0]], "video or bag")
        return frames
    folder = Path(folder)
    if not folder.is_dir():
        reason = "it is a file, and not a video or ROS bag by its extension" if folder.exists() else "folder not found"
        raise DataError(f"{folder}: not a folder of images ({reason})")
    candidates = folder.rglob("*") if recursive else folder.iterdir()
    paths = [
        p
        for p in candidates
        if p.suffix.lower() in IMAGE_EXTENSIONS
        and not _is_hidden(p.relative_to(folder))
        and (p.is_file() or _dangling_link(p))
    ]
    if not paths:
        raise DataError(f"{folder}: contains no images (looked for {', '.join(IMAGE_EXTENSIONS)})")
    paths = sorted(paths, key=lambda p: natural_key(p.relative_to(folder).as_posix()))
    note_inputs(paths)  # no output of the command is written over one (fdnet.io.refuse_writing_an_input)
    return paths


def _dangling_link(path: Path) -> bool:
    """Refuse an image name that is a symbolic link to nothing: skipping it would shift every
    later image's index, and a corrupt image stops the command too."""
    if path.is_symlink() and not path.exists():
        raise DataError(
            f"{path}: a symbolic link to {os.readlink(path)}, which does not exist; fix or remove the " "link"
        )
    return False


def has_images(folder: str | os.PathLike) -> bool:
    """Whether ``folder`` directly holds at least one image :func:`list_images` would list."""
    folder = Path(folder)
    try:
        return folder.is_dir() and any(
            p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".") and p.is_file()
            for p in folder.iterdir()
        )
    except OSError:
        return False


_BOMB_PIXELS = re.compile(r"\((\d+) pixels\)")


def _too_many_pixels(path: Path, pixels: int | None, detail: str = "") -> DataError:
    limit = Image.MAX_IMAGE_PIXELS
    count = f"{pixels:,} pixels" if pixels is not None else "more pixels than allowed"
    return DataError(
        f"{path}: image has {count}{detail}, over the limit of {limit:,} pixels "
        f"(PIL.Image.MAX_IMAGE_PIXELS); refusing to decode it, as it may be a decompression bomb"
    )


def _open(path: Path) -> Image.Image:
    """``Image.open`` whose decompression-bomb refusals are DataErrors naming the file.

    Pillow warns between ``MAX_IMAGE_PIXELS`` and twice that and raises above; fdnet refuses both
    (no place-recognition input has a quarter of a gigapixel), keeping Pillow's limit.
    """
    try:
        img = Image.open(path)
    except (FileNotFoundError, NotADirectoryError):
        from fdnet.data.frames import open_frame

        img = open_frame(path)  # a frame of a video or bag (fdnet.data.frames), or None
        if img is None:
            raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
        # The warning arrives as an exception when warnings are errors (python -W error).
        found = _BOMB_PIXELS.search(str(exc))
        raise _too_many_pixels(path, int(found.group(1)) if found else None) from exc
    limit = Image.MAX_IMAGE_PIXELS
    if limit is not None and img.width * img.height > limit:
        img.close()
        raise _too_many_pixels(path, img.width * img.height, f" ({img.width}x{img.height})")
    return img


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image from its header only (pixels are not decoded)."""
    path = Path(path)
    try:
        with _open(path) as img:
            return img.size
    except FileNotFoundError as exc:
        raise DataError(f"{path}: image file not found") from exc
    except (UnidentifiedImageError, OSError) as exc:
        raise DataError(f"{path}: cannot read image header ({exc})") from exc


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


def _to_uint8_rgb(img: Image.Image, path: Path, source_mode: str | None = None) -> np.ndarray:
    """8-bit images: exactly the bytes whose ``/ 255`` is :func:`_to_float_rgb`'s result. Images
    with more than 8 bits per channel (16-bit, 32-bit integer, float) are rounded to 8 bits."""
    if img.mode in ("I;16", "I;16B", "I;16L", "I", "F"):
        return np.rint(_to_float_rgb(img, path, source_mode) * 255.0).astype(np.uint8)
    if img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info):
        img = img.convert("RGBA")
        background = Image.new("RGBA", img.size, (0, 0, 0, 255))
        img = Image.alpha_composite(background, img)
    return np.asarray(img.convert("RGB"), dtype=np.uint8)


def load_image_uint8(path: str | os.PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """:func:`load_image` as uint8 RGB (H, W, 3): a quarter of the bytes, for pipelines that send
    images to a device and convert them there. For 8-bit files (nearly all), ``x / 255`` in
    float32 is exactly what :func:`load_image` returns; 16-bit and float files are rounded to 8
    bits."""
    return load_image(path, size, _convert=_to_uint8_rgb)


#: the largest image side fdnet reads or renders: every model here works at a few hundred pixels,
#: and one 100000x100000 RGB frame would need 120 GB before anything could say no
MAX_IMAGE_SIDE = 4096


def whole_number(value) -> int:
    """``value`` as an int when it is a whole number (an int of any size, a float or numeric text
    with no fraction; not a bool), else ValueError: how every size setting is read."""
    if isinstance(value, bool):
        raise ValueError(f"{value!r} is not a whole number")
    if isinstance(value, (float, np.floating)) and not float(value).is_integer():
        raise ValueError(f"{value!r} is not a whole number")
    return int(value)


def check_image_size(size, what: str) -> tuple[int, int]:
    """(height, width) as whole numbers in 1..MAX_IMAGE_SIDE, else a ConfigError naming ``what``:
    the one check for every size an image is brought to (descriptors' input sizes, trunk choices,
    synthetic frames), made before anything is allocated."""
    from fdnet.errors import ConfigError

    try:
        h, w = size
        h, w = whole_number(h), whole_number(w)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ConfigError(f"{what}: size {size!r} must be two whole numbers (height, width)") from exc
    if h < 1 or w < 1:
        raise ConfigError(f"{what}: size {h}x{w} must be positive")
    if h > MAX_IMAGE_SIDE or w > MAX_IMAGE_SIDE:
        raise ConfigError(
            f"{what}: size {h}x{w} is larger than any model here uses (at most {MAX_IMAGE_SIDE} " "pixels a side)"
        )
    return h, w


def load_image(path: str | os.PathLike, size: tuple[int, int] | None = None, *, _convert=None) -> np.ndarray:
    """Read one image as float32 RGB in [0, 1], shape (H, W, 3).

    ``size`` is (height, width); when given the image is resized with area-averaging
    (Pillow's BOX filter when shrinking, bilinear when enlarging).
    """
    convert = _convert or _to_float_rgb
    path = Path(path)
    try:
        with _open(path) as img:
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
            return convert(img, path, source_mode)
    except FileNotFoundError as exc:
        raise DataError(f"{path}: image file not found") from exc
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise DataError(f"{path}: cannot read image ({exc.__class__.__name__}: {exc})") from exc


def resize_array(array: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """An (H, W, 3) RGB array (uint8 0..255, or float in [0, 1]) brought to ``size`` exactly as
    :func:`load_image` brings an image file there (Pillow's BOX filter shrinking, bilinear
    enlarging): a frame given as an array and the same frame given as a PNG file are the same
    input. Float32 RGB in [0, 1]."""
    from fdnet.errors import DataError

    array = np.asarray(array)
    if array.ndim != 3 or array.shape[2] != 3:
        raise DataError(f"an image must be an (H, W, 3) RGB array, got an array of shape {array.shape}")
    height, width = check_image_size(size, "image size")
    shrinking = array.shape[1] >= width and array.shape[0] >= height
    resample = Image.Resampling.BOX if shrinking else Image.Resampling.BILINEAR
    if array.dtype == np.uint8:
        if array.shape[:2] != (height, width):
            array = np.asarray(Image.fromarray(array, "RGB").resize((width, height), resample))
        return array.astype(np.float32) / 255.0
    array = array.astype(np.float32)
    if array.size and (float(np.nanmax(array)) > 1.0 or float(np.nanmin(array)) < 0.0 or not np.isfinite(array).all()):
        raise DataError("a float image must hold values in [0, 1] (give uint8 for 0..255)")
    if array.shape[:2] == (height, width):
        return array
    channels = [np.asarray(Image.fromarray(array[..., c], "F").resize((width, height), resample)) for c in range(3)]
    return np.clip(np.stack(channels, axis=-1), 0.0, 1.0).astype(np.float32)


def load_images(paths: Sequence[str | os.PathLike], size: tuple[int, int], workers: int = 2) -> np.ndarray:
    """Read many images at one size into (N, H, W, 3) float32. Decoding runs in threads
    (Pillow releases the GIL while decoding)."""
    size = check_image_size(size, "images")
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


#: ITU-R BT.601 luminance weights (R, G, B), as OpenCV and Pillow use
GREY_WEIGHTS = (0.299, 0.587, 0.114)


def to_grey(images: np.ndarray) -> np.ndarray:
    """(..., 3) RGB -> (...) luminance (:data:`GREY_WEIGHTS`): the one grey conversion of images
    (descriptors, frame filters, loop-closure gates)."""
    r, g, b = GREY_WEIGHTS
    return images[..., 0] * r + images[..., 1] * g + images[..., 2] * b


def grey_levels(grey: np.ndarray) -> np.ndarray:
    """(N, ...) grey frames in [0, 1] -> (N, 2): each frame's mean (how bright) and standard
    deviation (how textured). The training filters' dark frames and loop closure's
    uninformative frames are thresholds on these."""
    grey = np.asarray(grey)
    if not len(grey):
        return np.zeros((0, 2), np.float32)
    flat = grey.reshape(len(grey), -1)
    return np.stack([flat.mean(axis=1), flat.std(axis=1)], axis=1)


def thumbnail_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean absolute difference of grey thumbnails over their last two axes (how much the view
    changed): the training filters' near-duplicates and loop closure's still frames are
    thresholds on it."""
    return np.abs(np.asarray(a, np.float32) - np.asarray(b, np.float32)).mean(axis=(-2, -1))
