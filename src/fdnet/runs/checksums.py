"""Checksums of a checkpoint generation's contents, so that a file damaged on disk (bit rot, a
bad copy) is refused when loaded instead of silently giving other weights.

The weights file (safetensors) records in its metadata the sha256 of its tensors (names, dtypes,
shapes and bytes) and of the generation's training state file; both are verified on load.
Generations written before these checksums existed carry none and load as before.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Mapping

import torch

from fdnet.errors import ConfigError

#: metadata keys of the weights file
TENSORS_KEY = "tensors_sha256"
STATE_KEY = "training_state_sha256"


def tensors_sha256(tensors: Mapping[str, torch.Tensor]) -> str:
    """sha256 over every tensor's name, dtype, shape and bytes, in name order."""
    digest = hashlib.sha256()
    for name in sorted(tensors):
        tensor = tensors[name].detach().to("cpu").contiguous()
        digest.update(f"{name}\0{tensor.dtype}\0{tuple(tensor.shape)}\0".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def bytes_sha256(data: bytes | memoryview) -> str:
    return hashlib.sha256(data).hexdigest()


def verify_tensors(path: Path, tensors: Mapping[str, torch.Tensor], metadata: Mapping[str, str]) -> None:
    """ConfigError naming ``path`` when its tensors are not the ones it was saved with."""
    expected = metadata.get(TENSORS_KEY)
    if expected is not None and tensors_sha256(tensors) != expected:
        raise ConfigError(
            f"{path}: the weights do not match the checksum saved with them: the file is damaged "
            "(bit rot or a bad copy); restore it from a backup or train again"
        )


def verify_state(path: Path, data: bytes, metadata: Mapping[str, str]) -> None:
    """ConfigError naming ``path`` when the training state file is not the one saved."""
    expected = metadata.get(STATE_KEY)
    if expected is not None and bytes_sha256(data) != expected:
        raise ConfigError(
            f"{path}: the training state does not match the checksum saved with it: the file is "
            "damaged (bit rot or a bad copy); resume from an earlier run or train again"
        )
