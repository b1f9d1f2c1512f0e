"""The trunk alone, the untrained numbers FDNet's content vector has to beat.

``trunk``: a frozen ImageNet map (any block of EfficientNet-Lite0, -Lite1 or -Lite2), flattened
and L2-normalised, compared by cosine. No projection: a Gaussian random projection (``conv3``)
only approximates these cosines.

``trunk-whitened``: the same map PCA-whitened to ``dim`` (L, default 512) dimensions, the
classical retrieval post-processing (Jégou & Chum, ECCV 2012; :mod:`fdnet.descriptors.whitening`),
learnt without labels from ``fit=DIR`` (every condition sub-folder, ``fit_frames=START:END`` of
each; the CLI's ``--fit``/``--fit-frames``) or, without one, from the reference images it is
matched against. ``settings()["fitted_on"]`` says which.

Both live with FDNet because they read an FDNet run's trunk settings: given a run
(``checkpoint``), the map that run's encoders read (same backbone, block and input size), so
``fdnet evaluate --method fdnet,trunk --checkpoint RUN`` compares the content vector with exactly
what it was learnt from; ``fdnet.descriptors`` then never imports a trained method's config.
Without one, the ``cpu`` preset's map (EfficientNet-Lite0 block 7 at 128x256).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from fdnet.descriptors.conv3 import Conv3Descriptor, Conv3Settings
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import ConfigError

log = logging.getLogger(__name__)

DEFAULT_BACKBONE = "efficientnet-lite0"
DEFAULT_BLOCK = 7
DEFAULT_INPUT_SIZE = (128, 256)
#: trunk-whitened's default length: the paper's FDNet_512
DEFAULT_WHITENED_DIM = 512


@dataclass(frozen=True)
class TrunkSettings(MethodSettings):
    method: ClassVar[str] = "trunk"
    #: an FDNet run (--checkpoint): its backbone, block and input size are the defaults
    checkpoint: str | None = None
    #: block of the backbone (default: the run's or choice's, else 7)
    block: int | None = None
    #: (height, width) images are resized to (default: the run's or choice's, else 128x256)
    input_size: tuple[int, int] | str | None = None
    #: bfloat16 autocast (none = where the device runs it natively)
    bf16: bool | None = None
    #: torch threads while describing (none = the process's setting)
    threads: int | None = None
    #: auto, cpu, cuda or cuda:N
    device: str | None = None
    #: efficientnet-lite0, -lite1 or -lite2 (default: the run's or choice's, else lite0)
    backbone: str | None = None
    #: a file from ``fdnet choose-trunk``: its backbone, block and input size are the defaults
    choice: str | None = None

    def check(self) -> None:
        checkpoint, choice = self.need_path("checkpoint"), self.need_path("choice")
        if checkpoint is not None and choice:
            raise ConfigError(
                f"{self.method}: give an FDNet run (checkpoint) or a trunk choice file (choice), " "not both"
            )
        self.need_backbone(optional=True)
        self.need_block(self.backbone, optional=True)
        self.need_size("input_size", optional=True)
        self.need_flag("bf16", optional=True)
        self.need_whole("threads", minimum=1, optional=True)
        self.need_device()


class TrunkDescriptor(Conv3Descriptor):
    """The frozen trunk's map alone. Settings: :class:`TrunkSettings`."""

    name = "trunk"
    Settings: ClassVar[type] = TrunkSettings

    def __init__(self, settings: TrunkSettings | None = None, **options):
        conf = self.Settings.build(settings, options)
        checkpoint, choice = conf.checkpoint, conf.choice
        backbone, block, input_size = conf.backbone, conf.block, conf.input_size
        self.run_dir = str(checkpoint) if checkpoint else None
        self.choice = str(Path(choice).resolve()) if choice else None
        if choice:
            from fdnet.methods.fdnet.trunk_choice import read_choice

            chosen = read_choice(choice)
            backbone = chosen["backbone"] if backbone is None else backbone
            block = chosen["block"] if block is None else block
            input_size = chosen["input_size"] if input_size is None else input_size
        if checkpoint is not None:
            from fdnet import runs
            from fdnet.methods.fdnet.config import FDNetRunConfig

            model = runs.load_config(checkpoint, FDNetRunConfig).model
            if model.backbone == "none":
                raise ConfigError(
                    f"{checkpoint}: this FDNet run learnt its encoders from pixels (no "
                    "model.backbone); there is no trunk to compare with"
                )
            backbone = model.backbone if backbone is None else backbone
            block = model.backbone_block if block is None else block
            input_size = tuple(model.input_size) if input_size is None else input_size
        # the run's or choice's values are checked as the user's are
        trunk = Conv3Settings(
            dim=0,
            block=DEFAULT_BLOCK if block is None else block,
            input_size=input_size or DEFAULT_INPUT_SIZE,
            bf16=conf.bf16,
            threads=conf.threads,
            device=conf.device,
            backbone=DEFAULT_BACKBONE if backbone is None else backbone,
        )
        super().__init__(trunk)
        self.conf = conf

    def settings(self) -> dict:
        out = super().settings()
        if self.run_dir:
            out["checkpoint"] = self.run_dir
        if self.choice:
            out["choice"] = self.choice
        return out


@dataclass(frozen=True)
class TrunkWhitenedSettings(TrunkSettings):
    method: ClassVar[str] = "trunk-whitened"
    #: L, the whitened length (at most the map's length and one fewer than the fitting images)
    dim: int = DEFAULT_WHITENED_DIM
    #: 1 = full whitening, 0 = PCA only (0.5: the best or within 0.01 of it on Nordland's validation pair)
    power: float = 0.5
    #: dataset folder to learn the whitening from (--fit; default the reference images)
    fit: str | None = None
    #: START:END frames of each of fit's conditions (--fit-frames)
    fit_frames: str | None = None

    def check(self) -> None:
        from fdnet.descriptors.fitting import check_fit_frames

        super().check()
        self.need_whole("dim", minimum=1)
        self.need_number("power", minimum=0)
        fit = self.need_path("fit")
        fit_frames = check_fit_frames(self.fit_frames, self.method)
        if fit_frames and not fit:
            raise ConfigError(
                f"{self.method}: fit_frames ({fit_frames}) needs fit=DIR (--fit DIR) to take " "the frames of"
            )


class TrunkWhitenedDescriptor(TrunkDescriptor):
    """``trunk``'s map PCA-whitened to ``dim`` (L) dimensions (see the module docstring).

    Settings: ``dim`` (L, default 512; at most the map's length and one fewer than the fitting
    images), ``power`` (1 = full whitening, 0 = PCA only; :mod:`fdnet.descriptors.whitening`; default
    0.5, the best or within 0.01 of the best on the Nordland validation pair for every block, so the
    row FDNet is measured against is the strongest one, docs/trunk.md),
    ``fit`` (dataset folder to learn from), ``fit_frames`` (START:END of each of its conditions),
    and every ``trunk`` setting. Without ``fit`` it learns from the reference images (``fit()``,
    which evaluation and matching call because ``needs_fit`` is then true). With ``fit`` the
    folder is checked at once and learnt from on first use (describe or fingerprint).
    """

    name = "trunk-whitened"

    Settings: ClassVar[type] = TrunkWhitenedSettings

    def __init__(self, settings: TrunkWhitenedSettings | None = None, **options):
        from fdnet.descriptors.fitting import check_fit_frames, fit_image_paths
        from fdnet.descriptors.whitening import max_whitening_dim

        super().__init__(settings, **options)
        conf = self.conf
        self.whitened_dim = int(conf.dim)
        self.power = float(conf.power)
        if self.whitened_dim > self.feature_dim:
            raise ConfigError(
                f"{self.name}: L = dim {self.whitened_dim} is larger than the map it whitens allows "
                f"({self.feature_map_text()} = {self.feature_dim} values); lower dim or choose "
                "a larger block or input size"
            )
        self.fit_frames = check_fit_frames(conf.fit_frames, f"{self.name}")
        fit = conf.fit
        self.fit_folder = str(fit) if fit else None
        self.fitted_on: str | None = None
        self._fit_paths: list[Path] | None = None
        self._whitening = None
        if self.fit_folder:
            self._fit_paths, self._fit_description = fit_image_paths(
                self.fit_folder, self.fit_frames, where=f"{self.name}: --fit"
            )
            limit = max_whitening_dim(len(self._fit_paths), self.feature_dim)
            if self.whitened_dim > limit:
                raise ConfigError(
                    f"{self.name}: L = dim {self.whitened_dim} is more than {len(self._fit_paths)} "
                    f"fitting images allow (at most {limit}: {self._fit_description}); lower dim "
                    "or fit on more images"
                )

    @property
    def min_fit_images(self) -> int:
        # centred vectors span one direction fewer than there are of them
        return self.whitened_dim + 1

    def feature_map_text(self) -> str:
        return " x ".join(str(s) for s in self._map_shape)

    @property
    def dim(self) -> int:
        return self.whitened_dim

    @property
    def needs_fit(self) -> bool:
        return self._whitening is None and self.fit_folder is None

    def settings(self) -> dict:
        out = super().settings()
        out.update(
            {
                "dim": self.whitened_dim,
                "map_dim": self.feature_dim,
                "whitening": "PCA whitening (Jegou & Chum 2012), L2 before and after",
                "power": self.power,
                "fit": self.fit_folder,
                "fit_frames": self.fit_frames,
                "fitted_on": self.fitted_on or (self._fit_description if self.fit_folder else None),
            }
        )
        return out

    def _raw(self, images: np.ndarray) -> np.ndarray:
        return super().describe(images)

    def _learn(self, raw: np.ndarray, description: str) -> None:
        from fdnet.descriptors.whitening import PCAWhitening

        self._whitening = PCAWhitening.fit(raw, self.whitened_dim, self.power, where=self.name)
        self.fitted_on = description
        log.info("%s: PCA whitening to %d dimensions learnt from %s", self.name, self.whitened_dim, description)

    def _ensure_fitted(self) -> None:
        if self._whitening is not None:
            return
        if self.fit_folder is None:
            raise ConfigError(
                f"{self.name}: no whitening yet; pass fit=DIR (--fit DIR) or fit() on the reference " "images first"
            )
        self._learn(self._describe_raw_paths(self._fit_paths), self._fit_description)

    def _describe_raw_paths(self, paths) -> np.ndarray:
        from fdnet.descriptors.pipeline import DescribeJob, PipelineSettings, describe_stream

        paths = list(paths)
        out = np.empty((len(paths), self.feature_dim), dtype=np.float32)
        for start, vectors in describe_stream(
            self, paths, PipelineSettings(batch_size=64), DescribeJob(self._raw, what=f"{self.name}: fitting")
        ):
            out[start : start + len(vectors)] = vectors
        return out

    def fit(self, images_or_paths) -> None:
        """Learn the whitening from these images (the reference images, when no ``fit`` folder was
        given): an (N, H, W, 3) array at ``input_size`` or a list of image paths."""
        from fdnet.descriptors.fitting import REFERENCE_IMAGES

        if isinstance(images_or_paths, np.ndarray):
            raw = (
                np.concatenate([self._raw(images_or_paths[i : i + 64]) for i in range(0, len(images_or_paths), 64)])
                if len(images_or_paths)
                else np.zeros((0, self.feature_dim), np.float32)
            )
        else:
            raw = self._describe_raw_paths(images_or_paths)
        self._learn(raw, f"{REFERENCE_IMAGES} ({len(raw)})")

    def describe(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) at ``input_size`` -> (N, L) whitened unit vectors."""
        self._ensure_fitted()
        return self._whitening.transform(self._raw(images))

    def fingerprint(self) -> str:
        # The whitening is part of what the vectors are: with a fit folder, learn it before hashing.
        # Without one, an unfitted copy hashes as it is (reproduce keys its caches on that plus the
        # reference images it is then fitted on), a fitted one with its whitening.
        if self.fit_folder:
            self._ensure_fitted()
        return super().fingerprint()
