"""Synthetic appearance conditions: extra training conditions made by changing the light and
colour of the real ones (an extension of FDNet's training data; the paper has none).

FDNet learns what tells conditions apart from the conditions it is given: the critic sees pairs
labelled same/different condition, the triplet loss separates conditions in v_a, and the residual
content head starts with the directions between the conditions' mean maps removed. A user with two
conditions (summer, winter) gives it one such direction. ``data.synthetic_conditions`` adds, for each
real condition C and each named change K, a condition ``C~K``: every image of C changed by K with a
strength drawn per image. FDNet then also has to drop what darkening, colour casts, haze/snow-like
brightening and contrast changes do to the trunk's map, changes that the conditions a user meets
later (night, dusk, fog) are made of.

What it uses: the training images alone (no labels, no correspondences). The changes are global
photometric maps applied to uint8 images, done once per run with a generator seeded by the run's
seed, so a resumed run rebuilds exactly the same conditions. Written by hand because they are a few
lines of tensor arithmetic, and no library here (no torchvision) offers a night-like darkening
with sensor noise.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np
import torch

from fdnet.errors import ConfigError

#: separates a real condition's name from the change applied to it: ``day~night``
SEPARATOR = "~"


def _uniform(generator: torch.Generator, n: int, low: float, high: float, *shape: int) -> torch.Tensor:
    return low + (high - low) * torch.rand((n, *shape), generator=generator)


def night(x: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Darker (gamma 1.8-3 on [0, 1], then x 0.25-0.6), a warm or cold cast of street and head
    lights (gains 0.8-1.2 per channel) and sensor noise (sigma 0.01-0.04)."""
    n = len(x)
    gamma = _uniform(g, n, 1.8, 3.0, 1, 1, 1)
    gain = _uniform(g, n, 0.25, 0.6, 1, 1, 1) * _uniform(g, n, 0.8, 1.2, 3, 1, 1)
    noise = torch.randn(x.shape, generator=g) * _uniform(g, n, 0.01, 0.04, 1, 1, 1)
    return x.pow(gamma) * gain + noise


def snow(x: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Brighter and flatter, towards a bluish white (blend weight 0.2-0.45), as snow cover and haze."""
    n = len(x)
    weight = _uniform(g, n, 0.2, 0.45, 1, 1, 1)
    white = torch.tensor([0.92, 0.95, 1.0]).view(1, 3, 1, 1)
    return x * (1 - weight) + white * weight


def cast(x: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """A colour cast: each channel scaled by 0.6-1.4 (dusk, sodium light, white balance)."""
    return x * _uniform(g, len(x), 0.6, 1.4, 3, 1, 1)


def contrast(x: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Contrast x 0.5-1.6 about the image mean, then gamma 0.5-2 (overcast, low sun, exposure)."""
    n = len(x)
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    stretched = ((x - mean) * _uniform(g, n, 0.5, 1.6, 1, 1, 1) + mean).clamp(0, 1)
    return stretched.pow(_uniform(g, n, 0.5, 2.0, 1, 1, 1))


CHANGES: dict[str, Callable[[torch.Tensor, torch.Generator], torch.Tensor]] = {
    "night": night,
    "snow": snow,
    "cast": cast,
    "contrast": contrast,
}


def check_changes(names) -> None:
    unknown = [n for n in names if n not in CHANGES]
    if unknown:
        raise ConfigError(
            f"data.synthetic_conditions: unknown change(s) {', '.join(map(repr, unknown))}; "
            f"choose from {', '.join(CHANGES)}"
        )
    if len(set(names)) != len(names):
        raise ConfigError(f"data.synthetic_conditions: {list(names)} names a change twice")


def changed(images: torch.Tensor, change: str, generator: torch.Generator, chunk: int = 256) -> torch.Tensor:
    """uint8 (N, 3, H, W) images with ``change`` applied, each image at its own drawn strength."""
    out = torch.empty_like(images)
    for start in range(0, len(images), chunk):
        x = images[start : start + chunk].float().div_(255.0)
        y = CHANGES[change](x, generator)
        out[start : start + chunk] = y.clamp_(0, 1).mul_(255.0).round_().to(torch.uint8)
    return out


def with_synthetic_conditions(data, changes, seed: int):
    """``data`` (a :class:`fdnet.training.data.TrainingImages`) with a condition ``C~K`` added for
    each real condition C and each change K, in that order (C-major); the real conditions first,
    unchanged."""
    changes = list(changes)
    check_changes(changes)
    if not changes:
        return data
    generator = torch.Generator().manual_seed(int(seed))
    names, images, frame_ids = list(data.names), list(data.images), list(data.frame_ids)
    for name, condition_images, ids in zip(data.names, data.images, data.frame_ids):
        for change in changes:
            names.append(f"{name}{SEPARATOR}{change}")
            images.append(changed(condition_images, change, generator))
            frame_ids.append(np.asarray(ids).copy())
    return replace(data, names=names, images=images, frame_ids=frame_ids)
