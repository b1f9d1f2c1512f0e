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

from pathlib import Path

import numpy as np

from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.errors import ConfigError, NotAvailableError, invalid_settings_are_config_errors

HOW_TO_SUPPLY_WEIGHTS = (
    "HybridNet's weights are distributed only as Caffe files and are not bundled with fdnet. "
    "To use it: get HybridNet.caffemodel (Chen et al., ICRA 2017), read its conv1..conv5 blobs "
    "(e.g. with caffe's Python API: net.params['conv4'][0].data, [1].data), save them as a "
    "safetensors file with keys conv1.weight, conv1.bias, ..., conv5.weight, conv5.bias "
    "(safetensors.numpy.save_file), and pass it with --weights FILE (Python: weights=FILE). "
    "See docs/baselines.md."
)


class HybridNetDescriptor(Descriptor):
    """HybridNet conv4 (Chen et al. ICRA 2017); needs ``weights=FILE`` (see module docstring).

    Settings: ``weights`` (required), ``layer`` (default "conv4"), ``dim`` (0 = raw map; > 0 =
    seeded GRP to that length), ``seed``, ``mean_bgr`` (Caffe pixel mean, 0..255; default the
    ImageNet mean 104, 117, 123; HybridNet's own mean file may differ slightly), ``input_size``
    (227x227), ``threads``, ``device`` (``auto``/``cpu``/``cuda``/``cuda:N``). Takes uint8 images.
    """

    name = "hybridnet"
    dot_product_similarity = True
    accepts_uint8 = True

    @invalid_settings_are_config_errors
    def __init__(self, weights: str | Path | None = None, layer: str = "conv4", dim: int = 0,
                 seed: int = 0, mean_bgr: tuple[float, float, float] = (104.0, 117.0, 123.0),
                 input_size: tuple[int, int] = (227, 227), threads: int | None = None,
                 device: str | None = None):
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
        self.mean_bgr = tuple(float(m) for m in mean_bgr)
        if len(self.mean_bgr) != 3:
            raise ConfigError(f"hybridnet: mean_bgr needs 3 values, got {mean_bgr}")
        self.input_size = (int(input_size[0]), int(input_size[1]))
        self.seed = int(seed)
        self.out_dim = int(dim)
        self.threads = threads
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
        return {"input_size": list(self.input_size), "weights": self.weights, "layer": self.layer,
                "dim": self.dim, "seed": self.seed, "mean_bgr": list(self.mean_bgr),
                "feature_map": list(self._map_shape)}

    def describe(self, images: np.ndarray) -> np.ndarray:
        import torch

        from fdnet.backbones import torch_threads

        images = np.asarray(images)
        if images.dtype != np.uint8:
            images = images.astype(np.float32, copy=False)
        with torch_threads(self.threads), torch.inference_mode():
            x = self.trunk.input_tensor(images, self.mean_bgr)
            maps = self.trunk.forward(x).reshape(len(images), -1).float()
            if maps.device.type != "cpu":
                if self._projection is not None:
                    maps = maps @ self._on_device.get(self._projection, maps.device)
                return l2_normalize(maps.cpu().numpy())
            flat = maps.numpy()
        if self._projection is not None:
            flat = flat @ self._projection
        return l2_normalize(flat)
