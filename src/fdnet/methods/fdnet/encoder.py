"""FDNet encoder (paper section 4.1): encoding blocks, then one fully connected layer.

Each encoding block is Conv2d(kernel 5, stride 2, padding 2) + BatchNorm2d + LeakyReLU(0.2), so
every block halves height and width exactly (when they are even). The content encoder E_c and
the appearance encoder E_a are two instances of this class: same structure, separate weights.
Dropout (paper: 0.5 in the encoders) is applied to the flattened feature map before the fully
connected layer, the usual place in DCGAN-style encoders.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn


def encoding_block(in_channels: int, out_channels: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, kernel_size=5, stride=2, padding=2, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.LeakyReLU(0.2, inplace=True),
    )


class Encoder(nn.Module):
    """(N, C, H, W) image -> (N, L) vector.

    ``input_size`` is (H, W); H and W must be divisible by ``2 ** len(widths)`` (checked by
    :func:`fdnet.methods.fdnet.model.validate_architecture` before anything is built).
    """

    def __init__(
        self,
        input_size: Sequence[int],
        widths: Sequence[int],
        vector_length: int,
        dropout: float = 0.5,
        in_channels: int = 3,
    ) -> None:
        super().__init__()
        blocks, channels = [], in_channels
        for width in widths:
            blocks.append(encoding_block(channels, width))
            channels = width
        self.blocks = nn.Sequential(*blocks)
        scale = 2 ** len(widths)
        self.feature_shape = (channels, int(input_size[0]) // scale, int(input_size[1]) // scale)
        flat = channels * self.feature_shape[1] * self.feature_shape[2]
        self.dropout = nn.Dropout(dropout)
        self.fc = nn.Linear(flat, vector_length)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        features = self.blocks(images)
        return self.fc(self.dropout(torch.flatten(features, 1)))
