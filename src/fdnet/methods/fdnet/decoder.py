"""FDNet decoder (paper section 4.1): concat(v_c, v_a) -> reconstructed image.

The paper shows upsampling blocks of ConvTranspose2d + BatchNorm + LeakyReLU but not the first
layer nor the output activation; our choices (settings-free, documented here):

* first layer: a fully connected layer from the 2L-long concatenation to the encoder's smallest
  feature map (C_last x H/2^n x W/2^n), followed by BatchNorm + LeakyReLU(0.2), the mirror image
  of the encoder's last FC (as in DCGAN generators);
* upsampling blocks: ConvTranspose2d(kernel 5, stride 2, padding 2, output_padding 1), which
  exactly doubles height and width (mirrors the encoder's k5/s2/p2 convolutions), + BatchNorm +
  LeakyReLU(0.2), one per encoder block, with the encoder's widths in reverse;
* the last upsampling block outputs the image channels with no BatchNorm and ``output`` as its
  activation: ``tanh`` for inputs scaled to [-1, 1], ``none`` (linear) for per-image
  standardised inputs (see ``FDNetConfig.input_norm``): the decoder always reconstructs exactly
  what the encoders see.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn


def upsampling_block(in_channels: int, out_channels: int, last: bool = False, output: str = "tanh") -> nn.Sequential:
    layers: list[nn.Module] = [
        nn.ConvTranspose2d(in_channels, out_channels, kernel_size=5, stride=2, padding=2, output_padding=1, bias=last)
    ]
    if not last:
        layers += [nn.BatchNorm2d(out_channels), nn.LeakyReLU(0.2, inplace=True)]
    elif output == "tanh":
        layers.append(nn.Tanh())
    elif output != "none":
        raise ValueError(f"unknown decoder output activation {output!r}")
    return nn.Sequential(*layers)


class Decoder(nn.Module):
    """(N, L_content + L_appearance) -> (N, C, H, W)."""

    def __init__(
        self,
        input_size: Sequence[int],
        widths: Sequence[int],
        vector_length: int,
        out_channels: int = 3,
        output: str = "tanh",
        content_length: int | None = None,
    ) -> None:
        super().__init__()
        scale = 2 ** len(widths)
        # v_c and v_a have the paper's one length L, unless the content head is the trunk's
        # flattened map (content_length).
        inputs = (vector_length if content_length is None else int(content_length)) + vector_length
        if not widths:
            # No upsampling blocks (an encoder reading a backbone's map directly): one linear
            # layer back to the map, which is signed and unbounded, so no BatchNorm or activation.
            self.feature_shape = (out_channels, int(input_size[0]), int(input_size[1]))
            self.fc = nn.Linear(inputs, out_channels * int(input_size[0]) * int(input_size[1]))
            self.blocks = nn.Identity()
            return
        self.feature_shape = (widths[-1], int(input_size[0]) // scale, int(input_size[1]) // scale)
        c, h, w = self.feature_shape
        self.fc = nn.Sequential(
            nn.Linear(inputs, c * h * w, bias=False),
            nn.BatchNorm1d(c * h * w),
            nn.LeakyReLU(0.2, inplace=True),
        )
        reversed_widths = list(widths)[::-1]
        blocks = []
        for i, width in enumerate(reversed_widths):
            last = i == len(reversed_widths) - 1
            out = out_channels if last else reversed_widths[i + 1]
            blocks.append(upsampling_block(width, out, last=last, output=output))
        self.blocks = nn.Sequential(*blocks)

    def forward(self, content: torch.Tensor, appearance: torch.Tensor) -> torch.Tensor:
        x = self.fc(torch.cat([content, appearance], dim=1))
        return self.blocks(x.view(x.shape[0], *self.feature_shape))
