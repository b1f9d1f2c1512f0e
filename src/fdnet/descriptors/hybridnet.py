"""HybridNet conv4 ("Conv4 fine-tuned" in the FDNet paper), only with the user's converted weights.

Source: Z. Chen, A. Jacobson, N. Sünderhauf, B. Upcroft, L. Liu, C. Shen, I. Reid, M. Milford,
"Deep learning features at scale for visual place recognition", ICRA 2017. HybridNet is CaffeNet
initialised from ImageNet and fine-tuned for place classification on the SPED dataset; its conv4
map (384 x 13 x 13 at 227x227) is the place descriptor, compared by cosine similarity.

Availability: the authors released HybridNet only as Caffe files (``HybridNet.caffemodel`` +
``deploy.prototxt``), which cannot be fetched here, and this project does not depend on Caffe.
:class:`HybridNetDescriptor` therefore runs only when given ``weights=FILE``: a state dict
(safetensors or a tensor-only torch file) with the Caffe layer names ``conv1.weight``,
``conv1.bias`` ... ``conv5.weight``, ``conv5.bias`` in CaffeNet shapes (conv2/4/5 in two groups).
Without it, it raises :class:`~fdnet.errors.NotAvailableError` saying how to make that file. No
other network is ever substituted under this name.

Difference from the original: none in the network; ``dim`` > 0 optionally adds the same seeded
Gaussian random projection as Conv3 (default 0 = the raw 64896-d conv4 map, as the original).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import NotAvailableError

HOW_TO_SUPPLY_WEIGHTS = (
    "HybridNet's weights are distributed only as Caffe files and are not bundled with fdnet. "
    "To use it: get HybridNet.caffemodel (Chen et al., ICRA 2017), read its conv1..conv5 blobs "
    "(e.g. with caffe's Python API: net.params['conv4'][0].data, [1].data), save them as a "
    "safetensors file with keys conv1.weight, conv1.bias, ..., conv5.weight, conv5.bias "
    "(safetensors.numpy.save_file), and pass it with --weights FILE (Python: weights=FILE). "
    "See docs/baselines.md."
)


@dataclass(frozen=True)
class HybridNetSettings(MethodSettings):
    method: ClassVar[str] = "hybridnet"
    #: the converted HybridNet weights file (--weights; required)
    weights: str | None = None
    #: the layer whose map is read
    layer: str = "conv4"
    #: 0 = the raw map; > 0 = a seeded Gaussian random projection to that length
    dim: int = 0
    #: seed of the projection
    seed: int = 0
    #: Caffe pixel mean, 0..255, blue green red (the ImageNet mean; HybridNet's own may differ slightly)
    mean_bgr: tuple[float, float, float] = (104.0, 117.0, 123.0)
    #: (height, width) images are resized to, [H, W] or HxW
    input_size: tuple[int, int] | str = (227, 227)
    #: torch threads while describing (none = the process's setting)
    threads: int | None = None
    #: auto, cpu, cuda or cuda:N
    device: str | None = None

    def check(self) -> None:
        self.need_path("weights")
        self.need_text("layer", choices=("conv1", "conv2", "conv3", "conv4", "conv5"))
        self.need_whole("dim", minimum=0)
        self.need_whole("seed", minimum=0)
        self.need_numbers("mean_bgr", length=3)
        self.need_size("input_size")
        self.need_whole("threads", minimum=1, optional=True)
        self.need_device()


class HybridNetDescriptor(Descriptor):
    """HybridNet conv4 (Chen et al. ICRA 2017); needs ``weights=FILE`` (see module docstring).
    Settings: :class:`HybridNetSettings`. Takes uint8 images."""

    name = "hybridnet"
    dot_product_similarity = True
    accepts_uint8 = True
    Settings: ClassVar[type] = HybridNetSettings

    def __init__(self, settings: HybridNetSettings | None = None, **options):
        conf = self.conf = HybridNetSettings.build(settings, options)
        weights, layer, device = conf.weights, conf.layer, conf.device
        if not weights:
            raise NotAvailableError("hybridnet: no weights given. " + HOW_TO_SUPPLY_WEIGHTS)
        if not Path(weights).is_file():
            raise NotAvailableError(f"{weights}: HybridNet weights file not found. " + HOW_TO_SUPPLY_WEIGHTS)
        from fdnet.backbones import DeviceCopies, resolve_device
        from fdnet.descriptors.alexnet import CaffeNetTrunk

        self.device = resolve_device("auto" if device is None else device, where=f"{self.name}: device")
        self._on_device = DeviceCopies()
        self.weights = str(weights)
        self.trunk = CaffeNetTrunk(self.weights, layer=layer, what="HybridNet", device=self.device)
        self.layer = layer
        self.mean_bgr = tuple(float(m) for m in conf.mean_bgr)
        self.input_size = conf.need_size("input_size")
        self.seed = int(conf.seed)
        self.out_dim = int(conf.dim)
        self.threads = conf.threads
        import torch

        with torch.inference_mode():
            probe = self.trunk.forward(torch.zeros(1, 3, *self.input_size, device=self.device))
        self._map_shape = tuple(probe.shape[1:])
        self.feature_dim = int(np.prod(self._map_shape))
        self._projection = None
        if self.out_dim:
            from fdnet.descriptors.conv3 import gaussian_random_projection

            self._projection = gaussian_random_projection(self.feature_dim, self.out_dim, self.seed)

    @property
    def dim(self) -> int:
        return self.out_dim or self.feature_dim

    def settings(self) -> dict:
        return {
            "input_size": list(self.input_size),
            "weights": self.weights,
            "layer": self.layer,
            "dim": self.dim,
            "seed": self.seed,
            "mean_bgr": list(self.mean_bgr),
            "feature_map": list(self._map_shape),
        }

    def describe(self, images: np.ndarray) -> np.ndarray:
        import torch

        from fdnet.backbones import torch_threads

        images = np.asarray(images)
        if images.dtype != np.uint8:
            images = images.astype(np.float32, copy=False)
        with torch_threads(self.threads), torch.inference_mode():
            x = self.trunk.input_tensor(images, self.mean_bgr)
            maps = self.trunk.run(x).reshape(len(images), -1).float()
            if maps.device.type != "cpu":
                if self._projection is not None:
                    maps = maps @ self._on_device.get(self._projection, maps.device)
                return l2_normalize(maps.cpu().numpy())
            flat = maps.numpy()
        if self._projection is not None:
            flat = flat @ self._projection
        return l2_normalize(flat)
