"""Classic hand-crafted descriptors: raw thumbnail, the SeqSLAM front end (SAD), HOG.

They need no training and no network, so they are the baselines every other method is compared
with, and the ones the tests and the synthetic-route demo can always run.

* ``raw`` (:class:`RawThumbnail`): a small grey thumbnail, mean-centred and L2-normalised, so
  the dot product is the normalised cross-correlation of the two thumbnails.
* ``sad`` (:class:`SeqSLAMFrontEnd`): SeqSLAM's single-image front end (Milford & Wyeth,
  "SeqSLAM: Visual route-based navigation for sunny summer days and stormy winter nights",
  ICRA 2012), with the settings of OpenSeqSLAM (Sünderhauf et al., ICRA workshop 2013):
  downsample, patch-normalise, compare by the mean absolute difference.
* ``hog`` (:class:`HOGDescriptor`): histogram of oriented gradients (Dalal & Triggs, CVPR 2005)
  with exactly the settings VPR-Bench's HOG baseline uses (Zaffar et al., IJCV 2021,
  ``VPR_Techniques/HOG_VPR.py``), computed with the same library (OpenCV), compared by cosine.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from fdnet.data.images import to_grey
from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import ConfigError, DataError


def _at_size(images: np.ndarray, size: tuple[int, int], what: str) -> np.ndarray:
    """Check a (N, H, W, 3) batch and bring it to ``size`` (area resampling when it is not there
    yet: callers normally load images at ``input_size`` already, see ``describe_paths``)."""
    images = np.asarray(images, dtype=np.float32)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise DataError(f"{what}: expected images shaped (N, H, W, 3), got {images.shape}")
    if images.shape[1:3] == tuple(size):
        return images
    import cv2

    h, w = size
    return (
        np.stack([cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA) for im in images])
        if len(images)
        else np.zeros((0, h, w, 3), np.float32)
    )


@dataclass(frozen=True)
class RawSettings(MethodSettings):
    method: ClassVar[str] = "raw"
    #: (height, width) of the thumbnail, [H, W] or HxW (32x64: SeqSLAM's, so raw and sad differ only
    #: by patch normalisation and the distance)
    size: tuple[int, int] | str = (32, 64)

    def check(self) -> None:
        self.need_size("size")


@dataclass(frozen=True)
class SADSettings(MethodSettings):
    method: ClassVar[str] = "sad"
    #: (height, width) of the thumbnail, [H, W] or HxW; multiples of patch_size
    size: tuple[int, int] | str = (32, 64)
    #: side of the square patches normalised to zero mean and unit variance
    patch_size: int = 8

    def check(self) -> None:
        h, w = self.need_size("size")
        patch = self.need_whole("patch_size", minimum=1)
        if h % patch or w % patch:
            raise ConfigError(f"sad: size {h}x{w} must be a multiple of patch_size {patch}")


@dataclass(frozen=True)
class HOGSettings(MethodSettings):
    method: ClassVar[str] = "hog"
    #: (height, width) images are resized to (the HOG window), [H, W] or HxW
    size: tuple[int, int] | str = (512, 512)
    #: cell side in pixels
    cell_size: int = 16
    #: block side in pixels (a multiple of the cell)
    block_size: int = 16
    #: step of the blocks in pixels
    block_stride: int = 8
    #: orientation bins (unsigned)
    orientations: int = 9
    #: the luminance instead of the colour image (OpenCV takes each pixel's strongest channel)
    grey: bool = False

    def check(self) -> None:
        h, w = self.need_size("size")
        cell, block, stride, bins = (
            self.need_whole(n) for n in ("cell_size", "block_size", "block_stride", "orientations")
        )
        self.need_flag("grey")
        check_opencv_hog((w, h), (block, block), (stride, stride), (cell, cell), bins, "hog")


class RawThumbnail(Descriptor):
    """Downsampled grey thumbnail, flattened, mean-centred and L2-normalised.

    The dot product of two such vectors is the zero-mean normalised cross-correlation of the
    thumbnails: invariant to a global brightness offset and gain, nothing more. The simplest
    possible baseline ("raw pixels").

    Settings: ``size`` (height, width) of the thumbnail, default 32x64 (the SeqSLAM resolution,
    so ``raw`` and ``sad`` differ only by patch normalisation and the distance).
    """

    name: ClassVar[str] = "raw"
    Settings: ClassVar[type] = RawSettings

    def __init__(self, settings: RawSettings | None = None, **options):
        self.conf = RawSettings.build(settings, options)
        self.input_size = self.conf.need_size("size")

    @property
    def dim(self) -> int:
        return self.input_size[0] * self.input_size[1]

    def describe(self, images: np.ndarray) -> np.ndarray:
        grey = to_grey(_at_size(images, self.input_size, self.name)).reshape(len(images), self.dim)
        grey = grey - grey.mean(axis=1, keepdims=True)
        return l2_normalize(grey)

    def settings(self) -> dict:
        return {"input_size": list(self.input_size), "grey": True, "mean_centred": True, "similarity": "cosine"}


def patch_normalize(grey: np.ndarray, patch_size: int, eps: float = 1e-4) -> np.ndarray:
    """(N, H, W) -> (N, H, W): every non-overlapping ``patch_size`` square patch made zero-mean
    and unit-variance (OpenSeqSLAM ``patchNormalize``, mode 1; MATLAB's ``std`` is the
    sample standard deviation, N-1, kept here). A flat patch (standard deviation below ``eps``,
    well under one 8-bit grey level) becomes all zeros: OpenSeqSLAM would divide by zero, and
    amplifying rounding noise would make it random. H and W must be multiples of ``patch_size``."""
    n, h, w = grey.shape
    s = patch_size
    patches = grey.reshape(n, h // s, s, w // s, s).astype(np.float32)
    mean = patches.mean(axis=(2, 4), keepdims=True)
    std = patches.std(axis=(2, 4), keepdims=True, ddof=1) if s > 1 else np.ones_like(mean)
    flat = std < eps
    out = np.where(flat, 0.0, (patches - mean) / np.where(flat, 1.0, std)).astype(np.float32)
    return out.reshape(n, h, w)


class SeqSLAMFrontEnd(Descriptor):
    """The SeqSLAM front end: grey, downsample, patch-normalise, sum of absolute differences.

    Source: Milford & Wyeth, ICRA 2012; settings as in OpenSeqSLAM (Sünderhauf, Neubert,
    Protzel, 2013): images downsampled to 32x64 (height x width) and normalised in 8x8 patches
    to zero mean and unit variance; two images are compared by the sum of absolute differences
    of their normalised pixels, divided by the number of pixels.

    Honest interface: SAD is not a dot product, so

    * :meth:`describe` returns the patch-normalised pixels themselves, **not** L2-normalised
      (normalising would change which image is closest under SAD);
    * :meth:`similarity` returns the **negative mean absolute difference** (higher = more
      similar; 0 for identical images), and ``dot_product_similarity`` is False so indexed
      (faiss inner-product) search refuses this method.

    Differences from OpenSeqSLAM: it stores ``127 + round((p - mean) / std)`` as 8-bit integers,
    which quantises the normalised values to whole standard deviations; we keep them as floats.
    Sequence matching (SeqSLAM's second half) is a separate step in ``fdnet.matching``; this is
    the single-image front end only. Sizes must be multiples of ``patch_size`` (OpenSeqSLAM
    leaves the remainder un-normalised; we refuse instead).
    """

    name: ClassVar[str] = "sad"
    #: negative mean absolute difference: 0 for identical images, below 0 otherwise
    similarity_ceiling: ClassVar[float] = 0.0
    dot_product_similarity: ClassVar[bool] = False

    Settings: ClassVar[type] = SADSettings

    def __init__(self, settings: SADSettings | None = None, **options):
        self.conf = SADSettings.build(settings, options)
        self.input_size = self.conf.need_size("size")
        self.patch_size = self.conf.need_whole("patch_size")

    @property
    def dim(self) -> int:
        return self.input_size[0] * self.input_size[1]

    def describe(self, images: np.ndarray) -> np.ndarray:
        grey = to_grey(_at_size(images, self.input_size, self.name))
        return patch_normalize(grey, self.patch_size).reshape(len(grey), self.dim).astype(np.float32)

    def similarity(self, queries: np.ndarray, references: np.ndarray, block: int = 1024) -> np.ndarray:
        """(Q, D), (R, D) -> (Q, R) negative mean absolute difference.

        Uses ``torch.cdist(p=1)`` (about 12x faster than broadcasting in numpy on the project's
        CPU) over blocks of ``block`` queries and references, so the (block, block, D)
        intermediate memory stays bounded whatever the sizes.
        """
        import torch

        q = torch.from_numpy(np.ascontiguousarray(queries, dtype=np.float32))
        r = torch.from_numpy(np.ascontiguousarray(references, dtype=np.float32))
        if q.ndim != 2 or r.ndim != 2 or q.shape[1] != r.shape[1]:
            raise DataError(
                f"sad: descriptors must be (Q, D) and (R, D) with equal D, got "
                f"{tuple(q.shape)} and {tuple(r.shape)}"
            )
        out = np.empty((q.shape[0], r.shape[0]), dtype=np.float32)
        scale = 1.0 / max(q.shape[1], 1)
        with torch.no_grad():
            for i in range(0, q.shape[0], block):
                for j in range(0, r.shape[0], block):
                    d = torch.cdist(q[i : i + block], r[j : j + block], p=1.0)
                    out[i : i + block, j : j + block] = (-scale * d).numpy()
        return out

    def settings(self) -> dict:
        return {
            "input_size": list(self.input_size),
            "patch_size": self.patch_size,
            "grey": True,
            "similarity": "negative mean absolute difference",
        }


def check_opencv_hog(window_wh, block_wh, stride_wh, cell_wh, bins, where: str) -> None:
    """Refuse (ConfigError naming ``where``) OpenCV HOG settings that crash the interpreter inside
    ``cv2.HOGDescriptor`` (a zero size or bin count: SIGSEGV / SIGFPE; a negative bin count: an
    exabyte allocation) or that OpenCV rejects later: every size is (width, height) in whole
    pixels >= 1, the cell divides the block, the block fits the window and steps along it by the
    stride, 1 <= bins <= 360. The one check for every OpenCV HOG fdnet builds (the ``hog``
    baseline, CALC's reconstruction target). Also refuses an OpenCV without ``HOGDescriptor``
    (OpenCV 5 keeps it in the contrib build that fdnet depends on)."""
    import cv2

    from fdnet.data.images import whole_number

    if not hasattr(cv2, "HOGDescriptor"):
        raise ConfigError(
            f"{where}: this OpenCV ({cv2.__version__}) has no HOGDescriptor; install "
            "opencv-contrib-python-headless, fdnet's OpenCV, in place of the OpenCV build installed"
        )

    named = {"window": window_wh, "block": block_wh, "block stride": stride_wh, "cell": cell_wh}
    sizes = {}
    for name, value in named.items():
        try:
            w, h = (whole_number(v) for v in value)
        except (TypeError, ValueError, OverflowError) as exc:
            raise ConfigError(f"{where}: HOG {name} size {value!r} must be two whole numbers (width, height)") from exc
        if w < 1 or h < 1 or w > 4096 or h > 4096:
            raise ConfigError(f"{where}: HOG {name} size {w}x{h} must be between 1 and 4096 pixels a side")
        sizes[name] = (w, h)
    if isinstance(bins, bool) or not isinstance(bins, (int, np.integer)) or not 1 <= int(bins) <= 360:
        raise ConfigError(f"{where}: HOG bins {bins!r} must be a whole number from 1 to 360")
    (ww, wh), (bw, bh), (sw, sh), (cw, ch) = (sizes[n] for n in named)
    if bw % cw or bh % ch:
        raise ConfigError(f"{where}: HOG block {bw}x{bh} must be a multiple of the cell {cw}x{ch}")
    if bw > ww or bh > wh or (ww - bw) % sw or (wh - bh) % sh:
        raise ConfigError(
            f"{where}: HOG block {bw}x{bh} must fit the window {ww}x{wh} and step along it by the "
            f"stride {sw}x{sh} (window - block a multiple of the stride)"
        )


class HOGDescriptor(Descriptor):
    """Histogram of oriented gradients over the whole image, compared by cosine similarity.

    Source: Dalal & Triggs, CVPR 2005. Settings are VPR-Bench's HOG baseline (Zaffar et al.,
    IJCV 2021, ``VPR_Techniques/HOG_VPR.py``): OpenCV ``cv2.HOGDescriptor`` with window 512x512,
    block 16x16, block stride 8x8, cell 16x16 (one cell per block), 9 unsigned orientation
    bins, OpenCV's default L2-Hys block normalisation; 63 x 63 blocks x 9 bins = 35721 values.
    We use OpenCV rather than scikit-image because only OpenCV's HOG has these exact settings
    (block stride of half a cell), so our numbers can be compared with VPR-Bench's.

    Like VPR-Bench, the colour image is used (OpenCV takes, per pixel, the gradient of the
    channel with the largest magnitude); ``grey=True`` uses the luminance instead. Images are
    resized to ``size`` by the loader (VPR-Bench uses ``cv2.resize``, bilinear; our loader uses
    Pillow box/bilinear, a small difference). Vectors are L2-normalised (VPR-Bench normalises in
    its cosine score instead; same ranking and scores).
    """

    name: ClassVar[str] = "hog"

    Settings: ClassVar[type] = HOGSettings

    def __init__(self, settings: HOGSettings | None = None, **options):
        conf = self.conf = HOGSettings.build(settings, options)
        self.input_size = conf.need_size("size")
        self.cell_size = int(conf.cell_size)
        self.block_size = int(conf.block_size)
        self.block_stride = int(conf.block_stride)
        self.orientations = int(conf.orientations)
        self.grey = conf.grey
        self._hog = None

    def _cv_hog(self):
        if self._hog is None:
            import cv2

            h, w = self.input_size
            b, s, c = self.block_size, self.block_stride, self.cell_size
            self._hog = cv2.HOGDescriptor((w, h), (b, b), (s, s), (c, c), self.orientations)
        return self._hog

    @property
    def dim(self) -> int:
        h, w = self.input_size
        blocks = ((h - self.block_size) // self.block_stride + 1) * ((w - self.block_size) // self.block_stride + 1)
        return blocks * (self.block_size // self.cell_size) ** 2 * self.orientations

    def describe(self, images: np.ndarray) -> np.ndarray:
        images = _at_size(images, self.input_size, self.name)
        if self.grey:
            images = to_grey(images)
        # OpenCV's HOG takes 8-bit images, as VPR-Bench feeds it (cv2.imread).
        as_bytes = np.clip(np.rint(images * 255.0), 0, 255).astype(np.uint8)
        hog = self._cv_hog()
        out = np.empty((len(images), self.dim), dtype=np.float32)
        for i, im in enumerate(as_bytes):
            out[i] = np.asarray(hog.compute(np.ascontiguousarray(im))).reshape(-1)
        return l2_normalize(out)

    def settings(self) -> dict:
        return {
            "input_size": list(self.input_size),
            "cell_size": self.cell_size,
            "block_size": self.block_size,
            "block_stride": self.block_stride,
            "orientations": self.orientations,
            "grey": self.grey,
            "implementation": "opencv",
            "similarity": "cosine",
        }
