"""CALC's place descriptor: a trained run directory -> L2-normalised vectors (cosine)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import ConfigError
from fdnet.methods.calc.config import load_run_config
from fdnet.methods.calc.model import build_network, to_grey_u8


@dataclass(frozen=True)
class CALCSettings(MethodSettings):
    method: ClassVar[str] = "calc"
    #: a run directory of ``fdnet train calc`` (--checkpoint; its best/ weights when it kept them)
    checkpoint: str | None = None
    #: bfloat16 autocast (none = where the device runs it natively)
    bf16: bool | None = None
    #: torch threads while describing (none = the process's setting)
    threads: int | None = None
    #: auto, cpu, cuda or cuda:N
    device: str | None = None

    def check(self) -> None:
        self.need_path("checkpoint")
        self.need_flag("bf16", optional=True)
        self.need_whole("threads", minimum=1, optional=True)
        self.need_device()


class CALCDescriptor(Descriptor):
    """CALC bottleneck (conv3 output, flattened), L2-normalised, compared by cosine.

    ``checkpoint``: a run directory written by ``fdnet train calc``. ``bf16``: autocast
    (default: on where the device has native bf16). ``threads``: torch threads while describing.
    ``device``: ``auto`` (a GPU when there is one), ``cpu``, ``cuda`` or ``cuda:N``; the grey
    uint8 images go there and are converted there.
    """

    name = "calc"
    accepts_uint8 = True

    Settings: ClassVar[type] = CALCSettings

    def __init__(self, settings: CALCSettings | None = None, **options):
        conf = self.conf = CALCSettings.build(settings, options)
        checkpoint, bf16, threads, device = conf.checkpoint, conf.bf16, conf.threads, conf.device
        import torch

        from fdnet.backbones import bf16_supported, resolve_device
        from fdnet.runs import load_weights

        if checkpoint is None:
            raise ConfigError(
                "method 'calc' needs a trained model: --checkpoint RUN_DIR "
                "(train one with `fdnet train calc --data DIR --out RUN_DIR`)"
            )
        from fdnet.runs import weights_folder, weights_note

        # a run directory means its best-validating weights when it kept them (best/)
        self.run_dir = weights_folder(checkpoint)
        self.config = load_run_config(self.run_dir)
        self.input_size = tuple(int(v) for v in self.config.model.input_size)
        self.device = resolve_device("auto" if device is None else device, where="calc: device")
        self.network = build_network(self.config.model).eval()
        metadata = load_weights(self.run_dir, {"calc": self.network})
        note = weights_note(checkpoint, self.run_dir, metadata.get("step"))
        if note:
            import logging

            logging.getLogger(__name__).info(note)
        self.network.to(self.device)
        self.step = int(metadata.get("step", 0))
        self.bf16 = bf16_supported(self.device) if bf16 is None else bool(bf16)
        self.threads = threads
        self._torch = torch

    @property
    def dim(self) -> int:
        return self.network.descriptor_dim

    def describe(self, images: np.ndarray) -> np.ndarray:
        from fdnet.backbones import autocast, torch_threads, unit_from_bytes

        torch = self._torch
        images = np.asarray(images)
        if images.dtype == np.uint8:
            # the float path's values exactly (u8 / 255 in float32), then CALC's own grey bytes
            images = images.astype(np.float32) / np.float32(255.0)
        grey = to_grey_u8(images)
        if grey.shape[-2:] != self.input_size:
            raise ConfigError(f"CALC expects images of size {self.input_size}, got {tuple(grey.shape[-2:])}")
        with torch_threads(self.threads), torch.inference_mode():
            # grey uint8 crosses to the device; / 255 there gives what the CPU path computed
            x = unit_from_bytes(torch.from_numpy(np.ascontiguousarray(grey))[:, None].to(self.device))
            with autocast(self.device, self.bf16):
                out = self.network.encode(x.contiguous(memory_format=torch.channels_last) if self.bf16 else x)
            return l2_normalize(out.float().cpu().numpy())

    def settings(self) -> dict:
        return {
            "input_size": list(self.input_size),
            "checkpoint": str(self.run_dir),
            "step": self.step,
            "dim": self.dim,
            "bf16": self.bf16,
        }
