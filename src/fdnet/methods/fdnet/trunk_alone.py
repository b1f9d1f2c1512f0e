"""The trunk alone (method ``trunk``): the frozen ImageNet map that FDNet's ``cpu`` preset reads,
flattened and L2-normalised, compared by cosine. The number FDNet's content vector has to beat.
It lives with FDNet because it reads an FDNet run's trunk settings; ``fdnet.descriptors`` then
never imports a trained method's config.

Given an FDNet run (``checkpoint``), it reads the map that run's encoders read (same backbone
block and input size), so ``fdnet evaluate --method fdnet,trunk --checkpoint RUN`` compares the
content vector with exactly what it was learnt from. Without one it is the ``cpu`` preset's map
(EfficientNet-Lite0 block 7 at 128x256). No projection: a Gaussian random projection (``conv3``)
only approximates these cosines.
"""

from __future__ import annotations

from pathlib import Path

from fdnet.descriptors.conv3 import Conv3Descriptor
from fdnet.errors import ConfigError, invalid_settings_are_config_errors

DEFAULT_BLOCK = 7
DEFAULT_INPUT_SIZE = (128, 256)


class TrunkDescriptor(Conv3Descriptor):
    name = "trunk"

    @invalid_settings_are_config_errors
    def __init__(self, checkpoint: str | Path | None = None, block: int | None = None,
                 input_size: tuple[int, int] | None = None, bf16: bool | None = None,
                 threads: int | None = None, device: str | None = None):
        self.checkpoint = str(checkpoint) if checkpoint else None
        if checkpoint is not None:
            from fdnet import runs
            from fdnet.methods.fdnet.config import TrainConfig

            model = runs.load_config(checkpoint, TrainConfig).model
            if model.backbone == "none":
                raise ConfigError(f"{checkpoint}: this FDNet run learnt its encoders from pixels (no "
                                  "model.backbone); there is no trunk to compare with")
            block = model.backbone_block if block is None else block
            input_size = tuple(model.input_size) if input_size is None else input_size
        super().__init__(dim=0, block=DEFAULT_BLOCK if block is None else int(block),
                         input_size=tuple(input_size or DEFAULT_INPUT_SIZE), bf16=bf16, threads=threads,
                         device=device)

    def settings(self) -> dict:
        out = super().settings()
        if self.checkpoint:
            out["checkpoint"] = self.checkpoint
        return out
