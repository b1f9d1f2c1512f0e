"""Conv3: a pretrained CNN's mid-level feature map, compressed by a Gaussian random projection.

Source: N. Sünderhauf, S. Shirazi, F. Dayoub, B. Upcroft, M. Milford, "On the performance of
ConvNet features for place recognition", IROS 2015: AlexNet's conv3 map (64896 values at 227x227)
is the most condition-robust layer; they compress it with a Gaussian random projection (GRP,
a Johnson-Lindenstrauss embedding that preserves cosine distances) and match by cosine
similarity. The FDNet paper (section 5.1.2) projects conv3 to the FDNet vector length.

Differences from the original:
- Default network: AlexNet/Caffe weights cannot be fetched here, so by default the map is
  EfficientNet-Lite0's block 7 (ImageNet; stride 16 like AlexNet conv3, 8 of 16 blocks deep:
  see :mod:`fdnet.backbones`), 80 x 14 x 14 = 15680 values at 224x224.
  With ``weights=FILE`` (a torchvision-layout AlexNet state dict) the original conv3 at 227x227
  is used instead.
- GRP: projected to ``dim`` (default 512) by a matrix with i.i.d. N(0, 1/dim) entries (the
  distribution scikit-learn's ``GaussianRandomProjection`` draws), generated from
  ``numpy.random.default_rng(seed)`` in float32. We generate it ourselves rather than calling
  scikit-learn because sklearn draws a float64 matrix (250 MB for AlexNet's 64896 x 512) and
  needs a ``fit`` on data just to learn the input width; ours is a pure function of
  (seed, input width, dim), so every process, and reference and query alike, use the same one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import ConfigError


def gaussian_random_projection(in_dim: int, out_dim: int, seed: int) -> np.ndarray:
    """(in_dim, out_dim) float32 matrix, entries N(0, 1/out_dim), deterministic in its arguments.

    Rows are drawn in blocks from one ``default_rng(seed)`` stream, so the result does not depend
    on available memory; ``x @ P`` preserves inner products in expectation (JL lemma).
    """
    rng = np.random.default_rng([int(seed), int(in_dim), int(out_dim)])
    matrix = rng.standard_normal((int(in_dim), int(out_dim)), dtype=np.float32)
    matrix *= np.float32(1.0 / np.sqrt(out_dim))
    return matrix


@dataclass(frozen=True)
class Conv3Settings(MethodSettings):
    method: ClassVar[str] = "conv3"
    #: projected length (0 = keep the raw flattened map)
    dim: int = 512
    #: block of ``backbone`` whose map is read
    block: int = 7
    #: (height, width) images are resized to (default 224x224; 227x227 with AlexNet weights)
    input_size: tuple[int, int] | str | None = None
    #: torchvision AlexNet state dict: its conv3 instead of the backbone (--weights)
    weights: str | None = None
    #: seed of the Gaussian random projection
    seed: int = 0
    #: bfloat16 autocast of the backbone (none = where the device runs it natively)
    bf16: bool | None = None
    #: torch threads while describing (none = the process's setting)
    threads: int | None = None
    #: auto, cpu, cuda or cuda:N (the projection runs there too)
    device: str | None = None
    #: efficientnet-lite0, -lite1 or -lite2
    backbone: str = "efficientnet-lite0"

    def check(self) -> None:
        self.need_whole("dim", minimum=0)
        self.need_size("input_size", optional=True)
        weights = self.need_path("weights")
        self.need_whole("seed", minimum=0)
        self.need_flag("bf16", optional=True)
        self.need_whole("threads", minimum=1, optional=True)
        self.need_device()
        self.need_backbone()
        if weights:
            self.need_whole("block", minimum=0)
        else:
            self.need_block(self.backbone)


class Conv3Descriptor(Descriptor):
    """Conv3 + GRP (Sünderhauf et al. IROS 2015). Settings: :class:`Conv3Settings`. Takes uint8
    images."""

    name = "conv3"
    dot_product_similarity = True
    accepts_uint8 = True
    Settings: ClassVar[type] = Conv3Settings

    def __init__(self, settings: Conv3Settings | None = None, **options):
        from fdnet.backbones import DeviceCopies, resolve_device

        conf = self.conf = Conv3Settings.build(settings, options)
        input_size, bf16, threads = conf.need_size("input_size", optional=True), conf.bf16, conf.threads
        self.out_dim = int(conf.dim)
        self.seed = int(conf.seed)
        self.threads = threads
        self.device = resolve_device("auto" if conf.device is None else conf.device, where=f"{self.name}: device")
        self._on_device = DeviceCopies()
        self.weights = str(conf.weights) if conf.weights else None
        if self.weights:
            from fdnet.descriptors.alexnet import AlexNetTrunk

            self._alexnet = AlexNetTrunk(self.weights, "conv3", device=self.device)
            self._extractor = None
            self.input_size = tuple(input_size) if input_size else (227, 227)
            self._map_shape = self._alexnet_map_shape(self.input_size)
        else:
            from fdnet.backbones import FeatureExtractor

            self._alexnet = None
            self._extractor = FeatureExtractor(
                block=int(conf.block), bf16=bf16, threads=threads, device=self.device, backbone=conf.backbone
            )
            self.input_size = tuple(input_size) if input_size else (224, 224)
            self._map_shape = (self._extractor.channels, *self._extractor.map_size(self.input_size))
        self.input_size = (int(self.input_size[0]), int(self.input_size[1]))
        self.feature_dim = int(np.prod(self._map_shape))
        self._projection = (
            gaussian_random_projection(self.feature_dim, self.out_dim, self.seed) if self.out_dim else None
        )

    @staticmethod
    def _alexnet_map_shape(size: tuple[int, int]) -> tuple[int, int, int]:
        def side(n: int) -> int:
            n = (n + 4 - 11) // 4 + 1  # conv1, stride 4, pad 2
            n = (n - 3) // 2 + 1  # pool
            return (n - 3) // 2 + 1  # conv2 keeps size; pool

        h, w = side(size[0]), side(size[1])
        if h < 1 or w < 1:
            raise ConfigError(f"conv3: input size {size} too small for AlexNet")
        return 384, h, w

    @property
    def dim(self) -> int:
        return self.out_dim or self.feature_dim

    def settings(self) -> dict:
        out = {
            "input_size": list(self.input_size),
            "dim": self.dim,
            "seed": self.seed,
            "feature_map": list(self._map_shape),
        }
        if self._alexnet is not None:
            out.update({"network": "alexnet (user weights)", "layer": "conv3", "weights": self.weights})
        else:
            out.update(self._extractor.settings())
        return out

    def feature_maps(self, images: np.ndarray):
        """(N, H, W, 3) float32 in [0, 1] or uint8 -> torch float32 (N, C, h, w) conv3(-like)
        maps on the descriptor's device."""
        import torch

        if self._alexnet is None:
            return self._extractor.features_tensor(images)
        from fdnet.backbones import torch_threads

        with torch_threads(self.threads), torch.inference_mode():
            return self._alexnet.run(self._alexnet.input_tensor(images)).float()

    def describe(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) at ``input_size``, float32 in [0, 1] or uint8 -> (N, dim) unit vectors."""
        images = np.asarray(images)
        if images.dtype != np.uint8:
            images = images.astype(np.float32, copy=False)
        if images.shape[1:3] != self.input_size:
            raise ValueError(f"conv3 expects images at {self.input_size}, got {images.shape[1:3]}")
        maps = self.feature_maps(images).reshape(len(images), -1)
        if maps.device.type == "cpu":
            # numpy on the CPU: the same BLAS, so the same vectors on every CPU run
            flat = maps.numpy()
            if self._projection is not None:
                flat = flat @ self._projection
            return l2_normalize(flat)
        import torch

        with torch.inference_mode():
            if self._projection is not None:
                maps = maps @ self._on_device.get(self._projection, maps.device)
            return l2_normalize(maps.cpu().numpy())
