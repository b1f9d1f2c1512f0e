"""Plain-torch AlexNet-family trunks, for users who bring their own weights.

No AlexNet, CaffeNet or HybridNet weights can be fetched here; these definitions exist so a user
who has a state-dict file can run the paper's original baselines exactly:

- :class:`AlexNetTrunk`: torchvision's AlexNet layout (Krizhevsky et al., NIPS 2012, in the
  one-GPU form of torchvision, "One weird trick", Krizhevsky 2014), with torchvision's key names
  (``features.0.weight`` ... ``features.10.bias``), so ``torchvision.models.alexnet(weights=...)
  .state_dict()`` saved by the user (``torch.save`` or safetensors) loads as it is. Classifier
  keys are ignored. Input: RGB, ImageNet mean/std, 227x227 (conv3: 384 x 13 x 13 = 64896 values,
  the size in Sünderhauf et al. IROS 2015).
- :class:`CaffeNetTrunk`: the BVLC CaffeNet layout (two-group conv2/4/5, pool before LRN) that
  HybridNet (Chen et al., ICRA 2017) fine-tunes; keys are Caffe's layer names ``conv1.weight`` ...
  ``conv5.bias`` (what caffemodel-to-numpy converters produce). Input: BGR, 0..255 minus a
  per-channel mean, 227x227. conv4: 384 x 13 x 13.

Weights files are read with safetensors (``.safetensors``) or ``torch.load(weights_only=True)``
(tensor-only; no arbitrary pickled code is executed).
"""

from __future__ import annotations

from pathlib import Path

from fdnet.backbones import CachePasses
from fdnet.errors import ConfigError, NotAvailableError

#: layer name -> index in ``features`` of torchvision's AlexNet (the ReLU follows at index + 1)
ALEXNET_CONV_INDEX = {"conv1": 0, "conv2": 3, "conv3": 6, "conv4": 8, "conv5": 10}
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: ImageNet pixel mean of the BVLC models, BGR order, 0..255 (ilsvrc_2012_mean averaged per channel)
CAFFE_MEAN_BGR = (104.0, 117.0, 123.0)


def _nn():
    import torch.nn as nn

    return nn


def build_alexnet_features():
    """torchvision's ``AlexNet.features`` as an ``nn.Sequential`` with the same indices."""
    nn = _nn()
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),  # 0 conv1
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(64, 192, kernel_size=5, padding=2),  # 3 conv2
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(192, 384, kernel_size=3, padding=1),  # 6 conv3
        nn.ReLU(inplace=True),
        nn.Conv2d(384, 256, kernel_size=3, padding=1),  # 8 conv4
        nn.ReLU(inplace=True),
        nn.Conv2d(256, 256, kernel_size=3, padding=1),  # 10 conv5
        nn.ReLU(inplace=True),
        nn.MaxPool2d(kernel_size=3, stride=2),
    )


def load_state_dict_file(path: str | Path, what: str) -> dict:
    """Read a tensor state dict from ``.safetensors`` or a torch file, with errors naming the file."""
    path = Path(path)
    if not path.is_file():
        raise NotAvailableError(f"{path}: {what} weights file not found")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            import torch

            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # any reader failure is a bad file, reported as such
        raise ConfigError(f"{path}: cannot read {what} weights ({exc.__class__.__name__}: {exc})") from exc
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ConfigError(f"{path}: expected a state dict (name -> tensor), got {type(state).__name__}")
    # Checkpoints saved from DataParallel prefix every key with "module."
    return {k[len("module.") :] if k.startswith("module.") else k: v for k, v in state.items()}


def _load_into(module, state: dict, prefix: str, path: Path, what: str) -> None:
    import torch

    expected = module.state_dict()
    picked = {}
    missing = []
    for key, ref in expected.items():
        value = state.get(prefix + key)
        if value is None:
            missing.append(prefix + key)
            continue
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != tuple(ref.shape):
            shape = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise ConfigError(f"{path}: {what} weight {prefix + key} has shape {shape}, expected {tuple(ref.shape)}")
        picked[key] = value.float()
    if missing:
        found = ", ".join(sorted(state)[:8])
        raise ConfigError(
            f"{path}: not {what} weights: missing {', '.join(missing[:6])}"
            f"{' ...' if len(missing) > 6 else ''} (file has: {found}{' ...' if len(state) > 8 else ''})"
        )
    module.load_state_dict(picked, strict=True)


class AlexNetTrunk:
    """torchvision-layout AlexNet up to (and including the ReLU of) ``layer`` ("conv1".."conv5"),
    loaded from the user's weights file."""

    def __init__(self, weights: str | Path, layer: str = "conv3", device=None):
        from fdnet.backbones import resolve_device

        if layer not in ALEXNET_CONV_INDEX:
            raise ConfigError(f"AlexNet layer {layer!r} unknown; one of {', '.join(ALEXNET_CONV_INDEX)}")
        path = Path(weights)
        full = build_alexnet_features()
        state = load_state_dict_file(path, "AlexNet")
        _load_into(full, state, "features.", path, "AlexNet (torchvision layout)")
        self.layer = layer
        self.device = resolve_device("cpu" if device is None else device)
        self.model = full[: ALEXNET_CONV_INDEX[layer] + 2].eval().to(self.device)
        for p in self.model.parameters():
            p.requires_grad_(False)
        self._passes = CachePasses()

    def run(self, x):
        """The maps of ``x`` (from :meth:`input_tensor`), in forward passes sized to the CPU's cache."""
        return self._passes.run(self.model, self.model, x)

    def input_tensor(self, images):
        """(N, H, W, 3) RGB, float32 in [0, 1] or uint8 -> ImageNet-normalised NCHW on the device."""
        from fdnet.backbones import images_to_device

        return images_to_device(images, self.device, mean=IMAGENET_MEAN, std=IMAGENET_STD)


def build_caffenet_features():
    """BVLC CaffeNet / HybridNet conv layers as an ``nn.ModuleDict`` keyed by Caffe layer name."""
    nn = _nn()
    return nn.ModuleDict(
        {
            "conv1": nn.Conv2d(3, 96, kernel_size=11, stride=4),
            "conv2": nn.Conv2d(96, 256, kernel_size=5, padding=2, groups=2),
            "conv3": nn.Conv2d(256, 384, kernel_size=3, padding=1),
            "conv4": nn.Conv2d(384, 384, kernel_size=3, padding=1, groups=2),
            "conv5": nn.Conv2d(384, 256, kernel_size=3, padding=1, groups=2),
        }
    )


class CaffeNetTrunk:
    """CaffeNet-layout trunk (HybridNet's architecture) up to the ReLU of ``layer``.

    Forward, as in the BVLC CaffeNet deploy prototxt: conv1-relu-pool(3,2)-LRN(5, 1e-4, 0.75),
    conv2-relu-pool(3,2)-LRN, conv3-relu, conv4-relu, conv5-relu. Caffe pools with ceil rounding,
    hence ``ceil_mode=True``.
    """

    ORDER = ("conv1", "conv2", "conv3", "conv4", "conv5")

    def __init__(self, weights: str | Path, layer: str = "conv4", what: str = "HybridNet", device=None):
        from fdnet.backbones import resolve_device

        if layer not in self.ORDER:
            raise ConfigError(f"{what} layer {layer!r} unknown; one of {', '.join(self.ORDER)}")
        path = Path(weights)
        self.convs = build_caffenet_features()
        state = load_state_dict_file(path, what)
        _load_into(self.convs, state, "", path, f"{what} (CaffeNet layout, keys conv1.weight ... conv5.bias)")
        self.device = resolve_device("cpu" if device is None else device)
        self.convs.eval().to(self.device)
        for p in self.convs.parameters():
            p.requires_grad_(False)
        self.layer = layer
        self._passes = CachePasses()

    def run(self, x):
        """:meth:`forward` in passes sized to the CPU's cache."""
        return self._passes.run(self.convs, self.forward, x)

    def forward(self, x):
        import torch.nn.functional as F

        for name in self.ORDER:
            x = F.relu(self.convs[name](x))
            if name == self.layer:
                return x
            if name in ("conv1", "conv2"):
                x = F.max_pool2d(x, kernel_size=3, stride=2, ceil_mode=True)
                x = F.local_response_norm(x, size=5, alpha=1e-4, beta=0.75, k=1.0)
        return x  # pragma: no cover - layer is always one of ORDER

    def input_tensor(self, images, mean_bgr=CAFFE_MEAN_BGR):
        """(N, H, W, 3) RGB, float32 [0, 1] or uint8 -> Caffe input on the trunk's device: BGR,
        0..255, mean subtracted."""
        import torch

        from fdnet.backbones import images_to_device

        x = images_to_device(images, self.device).flip(1) * 255.0
        return (x - torch.tensor(mean_bgr, dtype=torch.float32, device=x.device).view(1, 3, 1, 1)).contiguous()
