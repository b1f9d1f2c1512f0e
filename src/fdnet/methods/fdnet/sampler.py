"""Domain-balanced mini-batches (paper section 4.3: a mini-batch has shape (B, N_d)).

Each batch holds B images from each of the N_d conditions, drawn independently per condition:
the i-th image of one condition has nothing to do with the i-th image of another. FDNet never
uses cross-condition correspondences, so it is unsupervised with respect to place: the only
label it needs is which condition (domain) an image came from, which the folder gives.
"""

from __future__ import annotations

from typing import Sequence

import torch

from fdnet.errors import ConfigError


class DomainBalancedSampler:
    """Draws (N_d, B) index tensors: B distinct random indices into each condition's images.

    Within one condition the B indices are distinct (a batch-hard positive is never the anchor
    itself); across batches draws are independent. All randomness comes from ``generator`` so a
    run is reproducible and resumable (its state is saved with the checkpoint).
    """

    def __init__(
        self,
        sizes: Sequence[int],
        batch_per_domain: int,
        names: Sequence[str] | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        names = list(names) if names is not None else [str(i) for i in range(len(sizes))]
        if len(sizes) < 2:
            raise ConfigError(
                f"FDNet needs images of at least two conditions (domains) to train; got {len(sizes)} "
                f"({', '.join(names) or 'none'})"
            )
        if batch_per_domain < 2:
            raise ConfigError(
                "data.batch_per_domain must be >= 2 (batch-hard triplets need a positive), " f"got {batch_per_domain}"
            )
        for name, size in zip(names, sizes):
            if size < batch_per_domain:
                raise ConfigError(
                    f"condition {name!r} has {size} training images, fewer than "
                    f"data.batch_per_domain = {batch_per_domain}"
                )
        self.sizes = [int(s) for s in sizes]
        self.batch_per_domain = int(batch_per_domain)
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)

    @property
    def num_domains(self) -> int:
        return len(self.sizes)

    def sample(self) -> torch.Tensor:
        """(N_d, B) int64 indices, row d indexing condition d's images."""
        rows = [torch.randperm(size, generator=self.generator)[: self.batch_per_domain] for size in self.sizes]
        return torch.stack(rows)

    def domain_labels(self) -> torch.Tensor:
        """(N_d * B,) labels matching a batch flattened condition by condition."""
        return torch.arange(self.num_domains).repeat_interleave(self.batch_per_domain)
