"""FDNet's place descriptor: the content vector v_c of a trained run, L2-normalised, compared by
cosine similarity (paper section 4.2, eq. 11), i.e. the dot product of the unit vectors.

``RUN_DIR`` is the ``--out`` folder of ``fdnet train`` (final weights) or its ``best/``
sub-folder (the checkpoint with the best validation R@1, when training validated).

``device``: ``auto`` (default: a GPU when there is one), ``cpu``, ``cuda`` or ``cuda:N``. Images
(float32 in [0, 1], or uint8 as the streaming pipeline loads them) go to the device as they are
and are converted there. ``bf16``: bfloat16 autocast with channels_last tensors (False by
default: fp32 vectors, the same on every device; None = on where the device runs bf16 natively,
what ``fdnet extract`` uses).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from fdnet.descriptors.base import Descriptor
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import DataError, NotAvailableError


def _say_weights(given, folder, step) -> None:
    from fdnet.runs import weights_note

    note = weights_note(given, folder, step)
    if note:
        logging.getLogger(__name__).info(note)


@dataclass(frozen=True)
class FDNetSettings(MethodSettings):
    method: ClassVar[str] = "fdnet"
    #: the run directory of ``fdnet train`` (--checkpoint; its best/ weights when it kept them)
    checkpoint: str | None = None
    #: auto, cpu, cuda or cuda:N
    device: str | None = "auto"
    #: bfloat16 autocast with channels_last tensors (none = where the device runs it natively)
    bf16: bool | None = False
    #: images moved to the device at a time: one forward pass on a GPU (a compiled graph's fixed
    #: batch); on the CPU, passes sized to its cache (:class:`fdnet.backbones.CachePasses`)
    batch_size: int = 256
    #: torch.compile the content encoder (about a minute on 2 CPU cores: for large folders)
    compile: bool = False

    def check(self) -> None:
        self.need_path("checkpoint")
        self.need_device()
        self.need_flag("bf16", optional=True)
        self.need_whole("batch_size", minimum=1)
        self.need_flag("compile")


class FDNetDescriptor(Descriptor):
    """The content vector of a trained FDNet run. Settings: :class:`FDNetSettings`."""

    name: ClassVar[str] = "fdnet"
    dot_product_similarity: ClassVar[bool] = True
    accepts_uint8: ClassVar[bool] = True
    describes_appearance: ClassVar[bool] = True
    Settings: ClassVar[type] = FDNetSettings

    def __init__(self, settings: FDNetSettings | None = None, **options) -> None:
        conf = self.conf = FDNetSettings.build(settings, options)
        checkpoint, device, bf16 = conf.checkpoint, conf.device, conf.bf16
        if checkpoint is None:
            raise NotAvailableError(
                "method 'fdnet' needs a trained run: --checkpoint RUN_DIR " "(make one with `fdnet train`)"
            )
        import torch

        from fdnet.backbones import CachePasses, bf16_native, resolve_device
        from fdnet.methods.fdnet.config import FDNetRunConfig
        from fdnet.methods.fdnet.model import FDNet
        from fdnet.runs import load_config, load_weights, weights_folder

        # a run directory means its best-validating weights when it kept them (best/)
        self.run_dir = weights_folder(checkpoint)
        self.config = load_config(self.run_dir, FDNetRunConfig)
        self.device = resolve_device("auto" if device is None else device, where="fdnet: device")
        self.bf16 = bf16_native(self.device) if bf16 is None else bool(bf16)
        self.batch_size = int(conf.batch_size)
        model = FDNet(self.config.model)
        metadata = load_weights(self.run_dir, model.named_parts(), device="cpu")
        self.model = model.to(self.device).eval()
        if self.bf16:
            # bf16 convolutions are fastest on channels_last tensors (oneDNN, cuDNN); the stored
            # weights keep their values (and the fingerprint its bytes)
            self.model = self.model.to(memory_format=torch.channels_last)
        self.step = int(metadata["step"]) if metadata.get("step", "").isdigit() else None
        _say_weights(checkpoint, self.run_dir, self.step)
        self.input_size = tuple(int(v) for v in self.config.model.input_size)
        # torch.compile of FDNet.content (what it computes is unchanged: guards and graph breaks
        # keep its semantics); one graph for batches of exactly batch_size, so a shorter batch
        # is padded. Compiling takes about a minute on 2 CPU cores: for large folders.
        self.compiled = conf.compile
        self._passes = CachePasses()
        self._content = torch.compile(self.model.content, dynamic=False) if self.compiled else self.model.content

    @classmethod
    def from_run(cls, run_dir: str | Path, device: str | None = "auto", bf16: bool | None = False) -> "FDNetDescriptor":
        return cls(checkpoint=run_dir, device=device, bf16=bf16)

    @property
    def dim(self) -> int:
        return int(self.model.content_length)

    def _check(self, images) -> np.ndarray:
        images = np.asarray(images)
        if images.dtype != np.uint8:
            images = images.astype(np.float32, copy=False)
        if images.ndim != 4 or images.shape[-1] != 3:
            raise DataError(f"fdnet: expected images of shape (N, H, W, 3), got {images.shape}")
        if tuple(images.shape[1:3]) != self.input_size:
            raise DataError(
                f"fdnet: images are {images.shape[1]}x{images.shape[2]} (HxW) but this run takes "
                f"{self.input_size[0]}x{self.input_size[1]}; load them at descriptor.input_size"
            )
        return images

    def _vectors(self, images: np.ndarray, parts: tuple[str, ...]) -> list[np.ndarray]:
        """The requested vectors (``content``, ``appearance``) of ``images``, one model input per
        batch: the images cross to the device once for both."""
        import torch

        from fdnet.backbones import autocast, images_to_device

        images = self._check(images)
        out: dict[str, list] = {part: [] for part in parts}
        with torch.inference_mode():
            for start in range(0, len(images), self.batch_size):
                # NHWC images viewed as NCHW are channels_last already (what the model always got)
                x = images_to_device(images[start : start + self.batch_size], self.device, channels_last=True)
                with autocast(self.device, self.bf16):
                    for part in parts:
                        compiled = part != "appearance" and self.compiled
                        forward = self._compiled_content if part != "appearance" else self.model.appearance
                        # on the CPU in passes that fit its cache; a compiled graph takes one batch
                        # size (the whole batch elsewhere, the pass size on the CPU): filled up to it
                        pad = self.batch_size if compiled else 0
                        v = self._passes.run(self.model, forward, x, self.model.content if compiled else None, pad)
                        out[part].append(v.float())
        result = []
        for part in parts:
            if not out[part]:
                result.append(np.zeros((0, self.dim), dtype=np.float32))
            else:
                result.append(torch.cat(out[part]).cpu().numpy().astype(np.float32, copy=False))
        return result

    def _compiled_content(self, x):
        """``FDNet.content`` through torch.compile when asked; if compiling fails (no C++
        compiler, an unsupported platform), say so once and run it eagerly from then on."""
        if not self.compiled:
            return self.model.content(x)
        try:
            return self._content(x)
        except Exception as exc:  # torch._dynamo / inductor raise many types; all mean "not here"
            import warnings

            warnings.warn(
                f"fdnet: torch.compile of the content encoder failed ({type(exc).__name__}: "
                f"{str(exc).splitlines()[0] if str(exc) else ''}); running it without compiling",
                RuntimeWarning,
                stacklevel=2,
            )
            self.compiled = False
            self._content = self.model.content
            return self.model.content(x)

    def describe(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) at ``input_size``, float32 in [0, 1] or uint8 -> (N, L) unit content vectors."""
        from fdnet.descriptors.base import l2_normalize

        return l2_normalize(self._vectors(images, ("content",))[0])

    def describe_appearance(self, images: np.ndarray) -> np.ndarray:
        """(N, L) appearance vectors v_a, as the encoder outputs them (the triplet loss compares
        them by squared Euclidean distance, so they are not normalised)."""
        return self._vectors(images, ("appearance",))[0]

    def describe_both(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(unit content vectors, appearance vectors) of the same images, sent to the device once."""
        from fdnet.descriptors.base import l2_normalize

        content, appearance = self._vectors(images, ("content", "appearance"))
        return l2_normalize(content), appearance

    def settings(self) -> dict:
        return {
            "input_size": list(self.input_size),
            "vector_length": self.dim,
            "checkpoint": str(self.run_dir),
            "step": self.step,
            "preset": self.config.preset,
            "bf16": self.bf16,
        }


__all__ = ["FDNetDescriptor"]
