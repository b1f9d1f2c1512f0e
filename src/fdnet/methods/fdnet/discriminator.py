"""Pairwise appearance discriminator D_a (paper sections 3.2.3 and 4.1).

Three fully connected layers over concat(v_ci, v_cj) with one output. Trained as a WGAN-GP
critic (paper eq. 9), so the output is an unbounded score: no sigmoid. LeakyReLU(0.2) between
layers and dropout (paper: 0.25 "in the classifier") after each hidden layer. No BatchNorm: the
gradient penalty is defined per sample and batch normalisation would couple samples
(Gulrajani et al. 2017, "Improved Training of Wasserstein GANs", section 4).
"""

from __future__ import annotations

import torch
from torch import nn


class PairDiscriminator(nn.Module):
    """(N, L), (N, L) content vectors -> (N,) critic score ("same domain" is high)."""

    def __init__(self, vector_length: int, hidden: int = 512, dropout: float = 0.25) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(2 * vector_length, hidden),
            nn.LeakyReLU(0.2, inplace=True),
            nn.Dropout(dropout),
            nn.Linear(hidden, hidden),
            nn.LeakyReLU(0.2, inplace=True),
            nn.Dropout(dropout),
            nn.Linear(hidden, 1),
        )

    def forward_pairs(self, pairs: torch.Tensor) -> torch.Tensor:
        """(N, 2L) already-concatenated pairs -> (N,) (used for the gradient penalty)."""
        return self.net(pairs).squeeze(1)

    def forward(self, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
        return self.forward_pairs(torch.cat([first, second], dim=1))
