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
from pathlib import Path

import numpy as np

from fdnet.descriptors.conv3 import Conv3Descriptor
from fdnet.errors import ConfigError, invalid_settings_are_config_errors

log = logging.getLogger(__name__)

DEFAULT_BACKBONE = "efficientnet-lite0"
DEFAULT_BLOCK = 7
DEFAULT_INPUT_SIZE = (128, 256)
#: trunk-whitened's default length: the paper's FDNet_512
DEFAULT_WHITENED_DIM = 512


class TrunkDescriptor(Conv3Descriptor):
    """Settings: ``backbone`` (efficientnet-lite0/1/2), ``block``, ``input_size``, ``checkpoint``
    (an FDNet run: its backbone, block and input size are the defaults), ``choice`` (a file from
    ``fdnet choose-trunk``: the backbone, block and input size chosen on a validation pair are
    the defaults), ``bf16``, ``threads``, ``device``."""

    name = "trunk"

    @invalid_settings_are_config_errors
    def __init__(self, checkpoint: str | Path | None = None, block: int | None = None,
                 input_size: tuple[int, int] | None = None, bf16: bool | None = None,
                 threads: int | None = None, device: str | None = None, backbone: str | None = None,
                 choice: str | Path | None = None):
        from fdnet.backbones import check_backbone

        self.run_dir = str(checkpoint) if checkpoint else None
        self.choice = str(Path(choice).resolve()) if choice else None
        if checkpoint is not None and choice:
            raise ConfigError(f"{self.name}: give an FDNet run (checkpoint) or a trunk choice file (choice), not both")
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
                raise ConfigError(f"{checkpoint}: this FDNet run learnt its encoders from pixels (no "
                                  "model.backbone); there is no trunk to compare with")
            backbone = model.backbone if backbone is None else backbone
            block = model.backbone_block if block is None else block
            input_size = tuple(model.input_size) if input_size is None else input_size
        backbone = check_backbone(DEFAULT_BACKBONE if backbone is None else backbone, where=f"{self.name}: backbone")
        from fdnet.data.images import check_image_size

        input_size = check_image_size(input_size or DEFAULT_INPUT_SIZE, f"{self.name}: input_size")
        super().__init__(dim=0, block=DEFAULT_BLOCK if block is None else int(block),
                         input_size=input_size, bf16=bf16, threads=threads,
                         device=device, backbone=backbone)

    def settings(self) -> dict:
        out = super().settings()
        if self.run_dir:
            out["checkpoint"] = self.run_dir
        if self.choice:
            out["choice"] = self.choice
        return out


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

    @invalid_settings_are_config_errors
    def __init__(self, dim: int = DEFAULT_WHITENED_DIM, power: float = 0.5, fit: str | Path | None = None,
                 fit_frames: str | None = None, checkpoint: str | Path | None = None, block: int | None = None,
                 input_size: tuple[int, int] | None = None, bf16: bool | None = None,
                 threads: int | None = None, device: str | None = None, backbone: str | None = None,
                 choice: str | Path | None = None):
        from fdnet.descriptors.fitting import check_fit_frames, fit_image_paths
        from fdnet.descriptors.whitening import max_whitening_dim

        super().__init__(checkpoint=checkpoint, block=block, input_size=input_size, bf16=bf16, threads=threads,
                         device=device, backbone=backbone, choice=choice)
        if isinstance(dim, bool) or int(dim) != dim or int(dim) < 1:
            raise ConfigError(f"{self.name}: dim (L) must be a whole number >= 1, got {dim!r}")
        self.whitened_dim = int(dim)
        self.power = float(power)
        if not np.isfinite(self.power) or self.power < 0:
            raise ConfigError(f"{self.name}: power must be >= 0 (1 = full whitening, 0 = PCA only), got {power!r}")
        if self.whitened_dim > self.feature_dim:
            raise ConfigError(f"{self.name}: L = dim {self.whitened_dim} is larger than the map it whitens allows "
                              f"({self.feature_map_text()} = {self.feature_dim} values); lower dim or choose "
                              "a larger block or input size")
        self.fit_frames = check_fit_frames(fit_frames, f"{self.name}")
        if self.fit_frames and not fit:
            raise ConfigError(f"{self.name}: fit_frames ({self.fit_frames}) needs fit=DIR (--fit DIR) to take "
                              "the frames of")
        self.fit_folder = str(fit) if fit else None
        self.fitted_on: str | None = None
        self._fit_paths: list[Path] | None = None
        self._whitening = None
        if self.fit_folder:
            self._fit_paths, self._fit_description = fit_image_paths(self.fit_folder, self.fit_frames,
                                                                     where=f"{self.name}: --fit")
            limit = max_whitening_dim(len(self._fit_paths), self.feature_dim)
            if self.whitened_dim > limit:
                raise ConfigError(f"{self.name}: L = dim {self.whitened_dim} is more than {len(self._fit_paths)} "
                                  f"fitting images allow (at most {limit}: {self._fit_description}); lower dim "
                                  "or fit on more images")

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
        out.update({"dim": self.whitened_dim, "map_dim": self.feature_dim,
                    "whitening": "PCA whitening (Jegou & Chum 2012), L2 before and after",
                    "power": self.power,
                    "fit": self.fit_folder, "fit_frames": self.fit_frames,
                    "fitted_on": self.fitted_on or (self._fit_description if self.fit_folder else None)})
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
            raise ConfigError(f"{self.name}: no whitening yet; pass fit=DIR (--fit DIR) or fit() on the reference "
                              "images first")
        self._learn(self._describe_raw_paths(self._fit_paths), self._fit_description)

    def _describe_raw_paths(self, paths) -> np.ndarray:
        from fdnet.descriptors.pipeline import DescribeJob, PipelineSettings, describe_stream

        paths = list(paths)
        out = np.empty((len(paths), self.feature_dim), dtype=np.float32)
        for start, vectors in describe_stream(self, paths, PipelineSettings(batch_size=64),
                                              DescribeJob(self._raw, what=f"{self.name}: fitting")):
            out[start:start + len(vectors)] = vectors
        return out

    def fit(self, images_or_paths) -> None:
        """Learn the whitening from these images (the reference images, when no ``fit`` folder was
        given): an (N, H, W, 3) array at ``input_size`` or a list of image paths."""
        from fdnet.descriptors.fitting import REFERENCE_IMAGES

        if isinstance(images_or_paths, np.ndarray):
            raw = np.concatenate([self._raw(images_or_paths[i:i + 64]) for i in range(0, len(images_or_paths), 64)]) \
                if len(images_or_paths) else np.zeros((0, self.feature_dim), np.float32)
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
