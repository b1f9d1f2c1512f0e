"""FDNet's place descriptor: the content vector v_c of a trained run, L2-normalised, compared by
cosine similarity (paper section 4.2, eq. 11), i.e. the dot product of the unit vectors.

``RUN_DIR`` is the ``--out`` folder of ``fdnet train`` (final weights) or its ``best/``
sub-folder (the checkpoint with the best validation R@1, when training validated).
"""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

import numpy as np

from fdnet.descriptors.base import Descriptor
from fdnet.errors import DataError, NotAvailableError


class FDNetDescriptor(Descriptor):
    name: ClassVar[str] = "fdnet"
    dot_product_similarity: ClassVar[bool] = True

    def __init__(self, checkpoint: str | Path | None = None, device: str = "cpu", bf16: bool = False,
                 batch_size: int = 256) -> None:
        if checkpoint is None:
            raise NotAvailableError("method 'fdnet' needs a trained run: --checkpoint RUN_DIR (make one with `fdnet train`)")
        import torch

        from fdnet.methods.fdnet.model import FDNet
        from fdnet.runs import load_config, load_weights
        from fdnet.methods.fdnet.config import TrainConfig

        self.run_dir = Path(checkpoint)
        self.config = load_config(self.run_dir, TrainConfig)
        self.device = torch.device(device)
        self.bf16 = bool(bf16)
        self.batch_size = int(batch_size)
        model = FDNet(self.config.model)
        metadata = load_weights(self.run_dir, model.named_parts(), device="cpu")
        self.model = model.to(self.device).eval()
        self.step = int(metadata["step"]) if metadata.get("step", "").isdigit() else None
        self.input_size = tuple(int(v) for v in self.config.model.input_size)

    @classmethod
    def from_run(cls, run_dir: str | Path, device: str = "cpu", bf16: bool = False) -> "FDNetDescriptor":
        return cls(checkpoint=run_dir, device=device, bf16=bf16)

    @property
    def dim(self) -> int:
        return int(self.config.model.vector_length)

    def _vectors(self, images: np.ndarray, appearance: bool) -> np.ndarray:
        import contextlib

        import torch

        images = np.asarray(images, dtype=np.float32)
        if images.ndim != 4 or images.shape[-1] != 3:
            raise DataError(f"fdnet: expected images of shape (N, H, W, 3), got {images.shape}")
        if tuple(images.shape[1:3]) != self.input_size:
            raise DataError(f"fdnet: images are {images.shape[1]}x{images.shape[2]} (HxW) but this run takes "
                            f"{self.input_size[0]}x{self.input_size[1]}; load them at descriptor.input_size")
        out = []
        with torch.inference_mode():
            for start in range(0, len(images), self.batch_size):
                x = torch.from_numpy(images[start:start + self.batch_size]).permute(0, 3, 1, 2).to(self.device)
                cast = (torch.autocast(self.device.type, dtype=torch.bfloat16) if self.bf16
                        else contextlib.nullcontext())
                with cast:
                    v = self.model.appearance(x) if appearance else self.model.content(x)
                out.append(v.float().cpu().numpy())
        if not out:
            return np.zeros((0, self.dim), dtype=np.float32)
        return np.concatenate(out).astype(np.float32)

    def describe(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) in [0, 1] at ``input_size`` -> (N, L) unit content vectors."""
        from fdnet.descriptors.base import l2_normalize

        return l2_normalize(self._vectors(images, appearance=False))

    def describe_appearance(self, images: np.ndarray) -> np.ndarray:
        """(N, L) appearance vectors v_a, as the encoder outputs them (the triplet loss compares
        them by squared Euclidean distance, so they are not normalised)."""
        return self._vectors(images, appearance=True)

    def settings(self) -> dict:
        return {"input_size": list(self.input_size), "vector_length": self.dim, "checkpoint": str(self.run_dir),
                "step": self.step, "preset": self.config.preset, "bf16": self.bf16}


__all__ = ["FDNetDescriptor"]
