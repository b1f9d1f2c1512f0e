"""CALC's place descriptor: a trained run directory -> L2-normalised vectors (cosine)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.errors import ConfigError
from fdnet.methods.calc.config import load_run_config
from fdnet.methods.calc.model import build_network, to_grey_u8


class CALCDescriptor(Descriptor):
    """CALC bottleneck (conv3 output, flattened), L2-normalised, compared by cosine.

    ``checkpoint``: a run directory written by ``fdnet train-baseline calc``. ``bf16``: autocast
    (default: on where the CPU has native bf16). ``threads``: torch threads while describing.
    """

    name = "calc"

    def __init__(self, checkpoint: str | Path | None = None, bf16: bool | None = None,
                 threads: int | None = None):
        import torch

        from fdnet.backbones import bf16_supported
        from fdnet.runs import load_weights

        if checkpoint is None:
            raise ConfigError("method 'calc' needs a trained model: --checkpoint RUN_DIR "
                              "(train one with `fdnet train-baseline calc --data DIR --out RUN_DIR`)")
        self.checkpoint = Path(checkpoint)
        self.config = load_run_config(self.checkpoint)
        self.input_size = tuple(int(v) for v in self.config.model.input_size)
        self.network = build_network(self.config.model).eval()
        metadata = load_weights(self.checkpoint, {"calc": self.network})
        self.step = int(metadata.get("step", 0))
        self.bf16 = bf16_supported() if bf16 is None else bool(bf16)
        self.threads = threads
        self._torch = torch

    @property
    def dim(self) -> int:
        return self.network.descriptor_dim

    def describe(self, images: np.ndarray) -> np.ndarray:
        from fdnet.backbones import torch_threads

        torch = self._torch
        grey = to_grey_u8(images).astype(np.float32) / 255.0
        x = torch.from_numpy(np.ascontiguousarray(grey))[:, None]
        if x.shape[-2:] != self.input_size:
            raise ConfigError(f"CALC expects images of size {self.input_size}, got {tuple(x.shape[-2:])}")
        with torch_threads(self.threads), torch.inference_mode():
            if self.bf16:
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    out = self.network.encode(x.contiguous(memory_format=torch.channels_last))
            else:
                out = self.network.encode(x)
        return l2_normalize(out.float().numpy())

    def settings(self) -> dict:
        return {"input_size": list(self.input_size), "checkpoint": str(self.checkpoint), "step": self.step,
                "dim": self.dim, "bf16": self.bf16}
