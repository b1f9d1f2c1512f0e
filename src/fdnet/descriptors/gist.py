"""Gist: the spatial envelope of a scene as Gabor energies pooled on a coarse grid.

Source: A. Oliva and A. Torralba, "Modeling the shape of the scene: a holistic representation of
the spatial envelope", IJCV 42(3), 2001; the settings and pipeline follow the authors' reference
MATLAB code LMgist.m (Torralba, http://people.csail.mit.edu/torralba/code/spatialenvelope/):
grey image, intensity rescaled to 0..255, prefiltering (log intensity, whitening by removing a
Gaussian low-pass with ``fc_prefilt = 4``, local contrast normalisation), a frequency-domain
Gabor bank of 4 scales x 8 orientations applied with symmetric boundary extension of 32 pixels,
and the magnitude of each response averaged on a 4 x 4 grid: 32 x 16 = 512 values.

Differences from LMgist:
- the image is resized to ``image_size`` x ``image_size`` (default 128, LMgist's original size;
  newer LMgist uses 256) without LMgist's centre crop, so wide frames keep their sides;
- the 512-d vector is L2-normalised so that similarity is the cosine (LMgist returns it raw and
  users compare by Euclidean distance; for nearest-neighbour ranking of unit vectors the two are
  equivalent).

Hand-written because there is no maintained Python Gist package: PyPI's ``pyleargist`` and
``gist`` were last released in 2012 (pyleargist compiles LEAR's C implementation against FFTW).
The filter bank is a few lines of FFT arithmetic, vectorised here over the batch with numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import scipy.fft

from fdnet.data.images import to_grey
from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.descriptors.settings import MethodSettings, whole_number
from fdnet.errors import ConfigError


def gabor_bank(size: int, orientations_per_scale: tuple[int, ...]) -> np.ndarray:
    """LMgist's ``createGabor``: (F, size, size) transfer functions in FFT (unshifted) order.

    Filter ``l`` at scale ``i`` (0-based) and orientation ``j`` has parameters
    ``[0.35, 0.3 / 1.85**i, 16 * n_or**2 / 32**2, pi / n_or * j]``: a log-polar Gaussian around
    radial frequency ``0.3 / 1.85**i`` cycles/pixel and angle ``pi * j / n_or``.
    """
    n = size
    fx, fy = np.meshgrid(np.arange(-n // 2, n // 2), np.arange(-n // 2, n // 2))
    fr = np.fft.fftshift(np.sqrt(fx**2 + fy**2))
    theta = np.fft.fftshift(np.angle(fx + 1j * fy))
    filters = []
    for scale, n_or in enumerate(orientations_per_scale):
        for j in range(n_or):
            p0, p1, p2, p3 = 0.35, 0.3 / (1.85**scale), 16 * n_or**2 / 32**2, np.pi / n_or * j
            tr = theta + p3
            tr = tr + 2 * np.pi * (tr < -np.pi) - 2 * np.pi * (tr > np.pi)
            filters.append(np.exp(-10 * p0 * (fr / n / p1 - 1) ** 2 - 2 * p2 * np.pi * tr**2))
    return np.stack(filters).astype(np.float32)


def prefilter(images: np.ndarray, fc: float = 4.0) -> np.ndarray:
    """LMgist's ``prefilt``: (N, H, W) 0..255 -> whitened, locally contrast-normalised images.

    Log intensity, symmetric padding by 5, subtract a Gaussian low-pass (cut-off ``fc`` cycles/
    image), divide by 0.2 + local standard deviation from the same low-pass, crop the padding.
    """
    w = 5
    s1 = fc / np.sqrt(np.log(2))
    x = np.log(images.astype(np.float64) + 1.0)
    x = np.pad(x, ((0, 0), (w, w), (w, w)), mode="symmetric")
    _, sh, sw = x.shape
    n = max(sh, sw)
    n += n % 2
    x = np.pad(x, ((0, 0), (0, n - sh), (0, n - sw)), mode="symmetric")
    fx, fy = np.meshgrid(np.arange(-n // 2, n // 2), np.arange(-n // 2, n // 2))
    gf = np.fft.fftshift(np.exp(-(fx**2 + fy**2) / s1**2))
    out = x - np.real(np.fft.ifft2(np.fft.fft2(x) * gf))
    local_std = np.sqrt(np.abs(np.fft.ifft2(np.fft.fft2(out**2) * gf)))
    out = out / (0.2 + local_std)
    return out[:, w : sh - w, w : sw - w]


@dataclass(frozen=True)
class GistSettings(MethodSettings):
    method: ClassVar[str] = "gist"
    #: side of the square grey image, >= 16 and divisible by grid
    image_size: int = 128
    #: orientations per scale (one entry per scale)
    orientations: tuple[int, ...] = (8, 8, 8, 8)
    #: blocks per side of the grid the energies are averaged over
    grid: int = 4
    #: cut-off frequency of the pre-filter
    fc_prefilt: float = 4.0
    #: symmetric extension before filtering, in pixels
    boundary: int = 32
    #: images per vectorised FFT chunk (memory about batch x filters x (size+2b)^2 x 8 bytes)
    batch: int = 8

    def check(self) -> None:
        size = self.need_whole("image_size", minimum=16, maximum=4096)
        grid = self.need_whole("grid", minimum=1)
        if size % grid:
            raise ConfigError(f"gist: image_size {size} must be divisible by grid {grid}")
        orientations = self.orientations
        if (
            not isinstance(orientations, (list, tuple))
            or not orientations
            or any(whole_number(o) is None or whole_number(o) < 1 for o in orientations)
        ):
            self.refuse("orientations", "must be a list of whole numbers >= 1 (orientations per scale)")
        self.need_number("fc_prefilt", above=0)
        self.need_whole("boundary", minimum=0, maximum=4096)
        self.need_whole("batch", minimum=1)


class GistDescriptor(Descriptor):
    """Gist (Oliva & Torralba 2001, LMgist settings): 4 scales x 8 orientations x 4x4 grid = 512-d.
    Settings: :class:`GistSettings`."""

    name = "gist"
    dot_product_similarity = True
    Settings: ClassVar[type] = GistSettings

    def __init__(self, settings: GistSettings | None = None, **options):
        conf = self.conf = GistSettings.build(settings, options)
        image_size = int(conf.image_size)
        orientations = tuple(int(o) for o in conf.orientations)
        self.image_size = image_size
        self.orientations = orientations
        self.grid = int(conf.grid)
        self.fc_prefilt = float(conf.fc_prefilt)
        self.boundary = int(conf.boundary)
        self.batch = int(conf.batch)
        self.input_size = (image_size, image_size)
        self._filters = gabor_bank(image_size + 2 * self.boundary, orientations)

    @property
    def dim(self) -> int:
        return len(self._filters) * self.grid**2

    def settings(self) -> dict:
        return {
            "input_size": list(self.input_size),
            "orientations": list(self.orientations),
            "grid": self.grid,
            "fc_prefilt": self.fc_prefilt,
            "boundary": self.boundary,
        }

    def describe(self, images: np.ndarray) -> np.ndarray:
        images = np.asarray(images, dtype=np.float32)
        out = np.empty((len(images), self.dim), dtype=np.float32)
        for start in range(0, len(images), self.batch):
            out[start : start + self.batch] = self._describe_chunk(images[start : start + self.batch])
        return l2_normalize(out)

    def _describe_chunk(self, images: np.ndarray) -> np.ndarray:
        grey = to_grey(images).astype(np.float64)
        # LMgist stretches each image to 0..255 before the log; a flat (e.g. black) image stays 0.
        lo = grey.min(axis=(1, 2), keepdims=True)
        span = grey.max(axis=(1, 2), keepdims=True) - lo
        grey = 255.0 * (grey - lo) / np.where(span > 0, span, 1.0)
        x = prefilter(grey, self.fc_prefilt)
        b = self.boundary
        x = np.pad(x, ((0, 0), (b, b), (b, b)), mode="symmetric")
        # scipy.fft keeps single precision (numpy.fft would promote to complex128), halving the
        # cost of the 32 inverse transforms per image that dominate Gist's run time.
        spectrum = scipy.fft.fft2(x.astype(np.float32))
        # (N, 1, S, S) x (F, S, S) -> (N, F, S, S) responses; magnitude, crop the extension.
        response = np.abs(scipy.fft.ifft2(spectrum[:, None] * self._filters[None], overwrite_x=True))
        size = self.image_size
        response = response[:, :, b : b + size, b : b + size]
        # Average on a grid x grid partition (LMgist's downN with equal cells).
        cell = size // self.grid
        n, f = response.shape[:2]
        pooled = response.reshape(n, f, self.grid, cell, self.grid, cell).mean(axis=(3, 5))
        # LMgist orders features filter-major, then blocks in column-major (MATLAB) order.
        return pooled.transpose(0, 1, 3, 2).reshape(n, -1).astype(np.float32)
