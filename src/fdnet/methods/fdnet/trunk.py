"""An optional frozen ImageNet trunk in front of FDNet's encoders (an extension, not in the paper).

The paper trains E_c and E_a from scratch on hundreds of thousands of images. With the few
hundred training images a user often has per condition (Gardens Point: 100), an encoder learnt
from scratch sees too little to generalise; the usual remedy in VPR (NetVLAD, HybridNet, CALC's
successors) is to start from ImageNet features. ``FDNetConfig.backbone = "efficientnet-lite0"``
puts the first ``backbone_block + 1`` blocks of EfficientNet-Lite0 (or of the larger -lite1 or
-lite2: the only ImageNet weights available offline here, see :mod:`fdnet.backbones`) in front of
both encoders. The
whole FDNet objective is unchanged but acts on the trunk's feature map instead of pixels: the
encoders read the map, the decoder reconstructs the map (L_r is the MSE between maps), and the
critic and triplet loss act on the content and appearance vectors as they do without a trunk.

The trunk is frozen and always in eval mode: its weights come from the package (they are not
written to run directories), and BatchNorm statistics learnt on ImageNet must not drift towards
a few hundred training images.
"""

from __future__ import annotations

import torch
from torch import nn

from fdnet.backbones import (
    BACKBONES as PRETRAINED_BACKBONES,
)
from fdnet.backbones import (
    DEFAULT_BACKBONE,
    INPUT_MEAN,
    INPUT_STD,
    block_channels,
    block_stride,
    build_efficientnet_lite,
    check_block,
    map_size,
    trunk_forward,
)

#: what FDNet's model.backbone accepts: no trunk, or any shipped EfficientNet-Lite
BACKBONES = ("none", *PRETRAINED_BACKBONES)


def trunk_stride(block: int, backbone: str = DEFAULT_BACKBONE) -> int:
    """Input size / map size after ``block`` (ConfigError for a block that does not exist)."""
    return block_stride(backbone, block)


def trunk_map_size(input_size, block: int, backbone: str = DEFAULT_BACKBONE) -> tuple[int, int]:
    """(h, w) of the trunk's map for an (H, W) input (the backbone module's rule)."""
    return map_size(input_size, block, backbone)


class FrozenTrunk(nn.Module):
    """(N, 3, H, W) RGB in [0, 1] -> (N, C, h, w) float32 map of ``backbone`` (default
    EfficientNet-Lite0) after ``block``."""

    def __init__(self, block: int, backbone: str = DEFAULT_BACKBONE) -> None:
        super().__init__()
        self.backbone = backbone
        self.block = check_block(block, backbone)
        self.channels = block_channels(backbone, self.block)
        model = build_efficientnet_lite(backbone, pretrained=True)
        # Only the layers up to ``block`` run; dropping the rest keeps them out of .to() and memory.
        model._blocks = model._blocks[: self.block + 1]
        for name in ("_conv_head", "_bn1", "_fc", "_avg_pooling", "_dropout"):
            if hasattr(model, name):
                setattr(model, name, nn.Identity())
        self.net = model.requires_grad_(False).eval()
        self.register_buffer("mean", torch.tensor(INPUT_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(INPUT_STD).view(1, 3, 1, 1), persistent=False)

    def train(self, mode: bool = True) -> "FrozenTrunk":
        # Always eval: see the module docstring.
        return super().train(False)

    @torch.no_grad()
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return trunk_forward(self.net, (images - self.mean) / self.std, self.block).float()
