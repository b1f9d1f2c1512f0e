"""Optimisers the baselines choose by name in their configs (``train.optimizer``)."""

from __future__ import annotations

import torch

from fdnet.errors import ConfigError


def make_optimizer(params, train) -> torch.optim.Optimizer:
    """Adam or SGD from a config section with ``optimizer``, ``lr``, ``momentum``, ``weight_decay``."""
    if train.optimizer == "adam":
        return torch.optim.Adam(params, lr=train.lr)
    if train.optimizer == "sgd":
        return torch.optim.SGD(params, lr=train.lr, momentum=train.momentum, weight_decay=train.weight_decay)
    raise ConfigError(f"train.optimizer: {train.optimizer!r} is not one of adam, sgd")
