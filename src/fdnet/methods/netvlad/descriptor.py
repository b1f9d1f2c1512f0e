"""NetVLAD's place descriptor: a trained run directory -> L2-normalised vectors (cosine)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import ConfigError
from fdnet.methods.netvlad.config import load_run_config
from fdnet.methods.netvlad.model import build_network


@dataclass(frozen=True)
class NetVLADSettings(MethodSettings):
    method: ClassVar[str] = "netvlad"
    #: a run directory of ``fdnet train netvlad`` (--checkpoint; its best/ weights when it kept them)
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


class NetVLADDescriptor(Descriptor):
    """NetVLAD vector (optionally PCA-whitened), L2-normalised, compared by cosine.

    ``checkpoint``: a run directory written by ``fdnet train netvlad``. The frozen trunk
    comes from the installed EfficientNet-Lite0 ImageNet weights, the fine-tuned blocks and the
    VLAD layer from the run. ``bf16``: autocast (default: on where the device has native bf16).
    ``threads``: torch threads while describing. ``device``: ``auto`` (a GPU when there is one),
    ``cpu``, ``cuda`` or ``cuda:N``. Takes uint8 images (converted on the device).
    """

    name = "netvlad"
    accepts_uint8 = True

    Settings: ClassVar[type] = NetVLADSettings

    def __init__(self, settings: NetVLADSettings | None = None, **options):
        conf = self.conf = NetVLADSettings.build(settings, options)
        checkpoint, bf16, threads, device = conf.checkpoint, conf.bf16, conf.threads, conf.device
        from fdnet.backbones import FeatureExtractor, resolve_device
        from fdnet.runs import load_weights

        if checkpoint is None:
            raise ConfigError(
                "method 'netvlad' needs a trained model: --checkpoint RUN_DIR "
                "(train one with `fdnet train netvlad --data DIR --out RUN_DIR`)"
            )
        from fdnet.runs import weights_folder, weights_note

        # a run directory means its best-validating weights when it kept them (best/)
        self.run_dir = weights_folder(checkpoint)
        self.config = load_run_config(self.run_dir)
        model = self.config.model
        self.input_size = tuple(int(v) for v in model.input_size)
        # pretrained=False: every fine-tuned weight comes from the checkpoint
        self.device = resolve_device("auto" if device is None else device, where="netvlad: device")
        self.network = build_network(model, pretrained=False).eval()
        metadata = load_weights(self.run_dir, {"netvlad": self.network})
        note = weights_note(checkpoint, self.run_dir, metadata.get("step"))
        if note:
            import logging

            logging.getLogger(__name__).info(note)
        self.network.to(self.device)
        self.step = int(metadata.get("step", 0))
        self.extractor = FeatureExtractor(block=model.frozen_block, bf16=bf16, threads=threads, device=self.device)
        self.bf16 = self.extractor.bf16
        self.threads = threads

    @property
    def dim(self) -> int:
        return self.network.descriptor_dim

    def describe(self, images: np.ndarray) -> np.ndarray:
        import torch

        from fdnet.backbones import autocast, torch_threads

        images = np.asarray(images)
        if images.dtype != np.uint8:
            images = images.astype(np.float32, copy=False)
        if images.shape[1:3] != self.input_size:
            raise ConfigError(f"NetVLAD expects images of size {self.input_size}, got {images.shape[1:3]}")
        maps = self.extractor.features_tensor(images)
        with torch_threads(self.threads), torch.inference_mode():
            with autocast(self.device, self.bf16):
                out = self.network(maps.contiguous(memory_format=torch.channels_last) if self.bf16 else maps)
        return l2_normalize(out.float().cpu().numpy())

    def settings(self) -> dict:
        model = self.config.model
        return {
            "input_size": list(self.input_size),
            "checkpoint": str(self.run_dir),
            "step": self.step,
            "dim": self.dim,
            "clusters": model.clusters,
            "frozen_block": model.frozen_block,
            "last_block": model.last_block,
            "pca_dim": model.pca_dim,
            "bf16": self.bf16,
        }
