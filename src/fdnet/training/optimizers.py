"""Optimisers the baselines choose by name in their configs (``optim.optimizer``)."""

from __future__ import annotations

import torch

from fdnet.errors import ConfigError


def make_optimizer(params, optim) -> torch.optim.Optimizer:
    """Adam or SGD from a config section with ``optimizer``, ``lr``, ``momentum``, ``weight_decay``."""
    if optim.optimizer == "adam":
        return torch.optim.Adam(params, lr=optim.lr)
    if optim.optimizer == "sgd":
        return torch.optim.SGD(params, lr=optim.lr, momentum=optim.momentum, weight_decay=optim.weight_decay)
    raise ConfigError(f"optim.optimizer: {optim.optimizer!r} is not one of adam, sgd")
