"""NetVLAD's training step on the shared loop: the triplet loss on the training split's
frame-aligned ground truth (queries and references from different conditions), with the
hardest of a sample of negatives mined from a periodically refreshed descriptor cache.

NetVLAD is supervised: positives are the frames within ``data.tolerance`` of the query's frame in
another condition. The frozen trunk's maps are computed once per run. What a resume needs beyond
weights and the optimiser: the numpy generator and the mining cache as it was (so the resumed
run mines exactly what the uninterrupted one would have). In a distributed run (torchrun) rank r's
generator is seeded with ``runtime.seed + r`` (other triplets on every rank; the cache, computed
from the shared weights, is the same on all) and the gradients are averaged before each step.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from fdnet.backbones import FeatureExtractor
from fdnet.errors import ConfigError, DataError
from fdnet.methods.netvlad import model as netvlad
from fdnet.methods.netvlad.config import NetVLADRunConfig
from fdnet.methods.settings import check_finite, check_validation_pair
from fdnet.training.data import TrainingImages, route_images, training_route
from fdnet.training.distributed import loss_text
from fdnet.training.loop import (
    LoopSettings,
    TrainingMethod,
    autocast,
    numpy_rng_state,
    set_numpy_rng_state,
    training_device,
    training_precision,
)
from fdnet.training.optimizers import make_optimizer


def aligned_frame_ids(data: TrainingImages, root: str) -> np.ndarray:
    """Frame ids shared by every condition (frame-aligned ground truth needs identical ones)."""
    if len(data.names) < 2:
        raise DataError(
            f"{root}: NetVLAD trains on query/reference pairs from different conditions; "
            f"give at least two (got {', '.join(data.names) or 'none'})"
        )
    frame_ids = data.frame_ids[0]
    for name, ids in zip(data.names[1:], data.frame_ids[1:]):
        if len(ids) != len(frame_ids) or not np.array_equal(ids, frame_ids):
            raise DataError(
                f"{Path(root) / name} has {len(ids)} frames but {Path(root) / data.names[0]} has "
                f"{len(frame_ids)}: frame-aligned ground truth needs the same frames in every "
                "training condition"
            )
    return frame_ids


def triplet_candidates(frame_ids: np.ndarray, tolerance: int, negative_distance: int):
    """Per frame: indices of its positives (|d| <= tolerance) and negatives (|d| > negative_distance)."""
    gap = np.abs(frame_ids[:, None] - frame_ids[None, :])
    positives = [np.flatnonzero(row <= tolerance) for row in gap]
    negatives = [np.flatnonzero(row > negative_distance) for row in gap]
    return positives, negatives


def validate(config: NetVLADRunConfig) -> None:
    model_cfg, train, data = config.model, config.train, config.data
    netvlad.check_model_config(model_cfg)
    if train.batch_size < 1 or train.steps < 0 or train.hard_negatives < 1 or train.negatives_sampled < 1:
        raise ConfigError("NetVLAD train.batch_size, hard_negatives and negatives_sampled must be >= 1, steps >= 0")
    if data.tolerance < 0 or train.negative_distance < data.tolerance:
        raise ConfigError(
            f"NetVLAD negatives must lie farther than the positives: train.negative_distance "
            f"({train.negative_distance}) must be >= the tolerance ({data.tolerance}) >= 0"
        )
    if train.cache_refresh < 1:
        raise ConfigError("NetVLAD train.cache_refresh must be >= 1")
    check_finite("optim.lr", config.optim.lr, positive=True)
    for name in ("checkpoint_every", "log_every"):
        if getattr(config.runtime, name) < 1:
            raise ConfigError(f"runtime.{name} must be >= 1")
    check_finite("train.margin", train.margin)
    v = config.validation
    check_validation_pair(v)


class NetVLADTraining(TrainingMethod):
    name = "netvlad"
    log_columns = ("loss", "active_triplets")
    rank_state_keys = ("numpy_rng",)  # the mining cache is the same on every rank

    def __init__(self, config: NetVLADRunConfig, data: TrainingImages) -> None:
        validate(config)
        self.config = config
        model_cfg, train, rt = config.model, config.train, config.runtime
        self.input_size = tuple(int(v) for v in model_cfg.input_size)
        self.frame_ids = aligned_frame_ids(data, config.data.root)
        self.positives, self.negatives = triplet_candidates(
            self.frame_ids, config.data.tolerance, train.negative_distance
        )
        lonely = [int(self.frame_ids[i]) for i, n in enumerate(self.negatives) if len(n) == 0]
        if lonely:
            raise DataError(
                f"{config.data.root}: frame {lonely[0]} has no negative (no training frame is more "
                f"than {train.negative_distance} frames away); train on more frames or lower "
                "train.negative_distance"
            )
        if len(self.frame_ids) < train.batch_size:
            raise DataError(
                f"{config.data.root}: {len(self.frame_ids)} training frames, fewer than one batch "
                f"({train.batch_size}); add frames or lower train.batch_size"
            )
        if model_cfg.pca_dim and len(self.frame_ids) * len(data.names) <= model_cfg.pca_dim:
            raise ConfigError(
                f"NetVLAD model.pca_dim {model_cfg.pca_dim} needs more training images than that "
                f"(have {len(self.frame_ids) * len(data.names)}); lower it or set 0"
            )
        self.device = training_device(rt)
        self.use_bf16 = training_precision(rt, self.device, native_only=True)
        self.rng = np.random.default_rng(self.distributed.rank_seed(rt.seed))  # per rank: other triplets
        torch.manual_seed(rt.seed)
        self.network = netvlad.build_network(model_cfg, pretrained=True).to(self.device)
        t_prep = time.perf_counter()
        self.extractor = FeatureExtractor(block=model_cfg.frozen_block, bf16=self.use_bf16, device=self.device)
        self.conditions = list(data.names)
        self.maps = {c: self._trunk_maps(images) for c, images in zip(data.names, data.images)}
        self.all_maps = torch.cat([self.maps[c] for c in self.conditions])
        self.log(
            f"NetVLAD: {len(self.frame_ids)} frames x {len(self.conditions)} conditions "
            f"({', '.join(self.conditions)}) on {self.device}, trunk maps {tuple(self.all_maps.shape[1:])} "
            f"cached in {time.perf_counter() - t_prep:.0f} s"
        )
        parameters = [p for p in self.network.parameters() if p.requires_grad]
        self.optimizer = make_optimizer(parameters, config.optim)
        self.cache: dict[str, np.ndarray] = {}
        self.cache_step = -1

    def _trunk_maps(self, images: torch.Tensor, chunk: int = 64) -> torch.Tensor:
        # uint8 images travel to the device as they are and are scaled there (images_to_device)
        parts = [
            self.extractor.features_tensor(images[i : i + chunk].permute(0, 2, 3, 1).numpy())
            for i in range(0, len(images), chunk)
        ]
        return torch.cat(parts, dim=0)

    def _describe_maps(self, maps: torch.Tensor, chunk: int = 128) -> np.ndarray:
        """No-gradient descriptors of cached maps (for mining, k-means and PCA)."""
        out = []
        with torch.no_grad(), autocast(self.device, self.use_bf16):
            for i in range(0, len(maps), chunk):
                out.append(self.network.vlad_vectors(maps[i : i + chunk]).float())
        return torch.cat(out).cpu().numpy()

    # ------------------------------------------------------------------ loop interface
    def modules(self):
        return {"netvlad": self.network}

    def optimizers(self):
        return {"netvlad": self.optimizer}

    def loop_settings(self) -> LoopSettings:
        rt = self.config.runtime
        return LoopSettings(self.config.train.steps, rt.checkpoint_every, rt.log_every, self.config.validation.every)

    def start(self) -> None:
        """Cluster centres by k-means on L2-normalised local features of the last fine-tuned block."""
        import faiss

        train = self.config.train
        self.network.eval()
        clusters = self.network.vlad.centroids.shape[0]
        order = self.rng.permutation(len(self.all_maps))[: min(len(self.all_maps), 512)]
        with torch.no_grad():
            local = torch.cat(
                [self.network.local_features(self.all_maps[order[i : i + 64]]) for i in range(0, len(order), 64)]
            )
        local = local.permute(0, 2, 3, 1).reshape(-1, local.shape[1]).cpu().numpy().astype(np.float32)
        local /= np.maximum(np.linalg.norm(local, axis=1, keepdims=True), 1e-12)
        if len(local) < clusters:
            raise DataError(
                f"only {len(local)} local features for {clusters} NetVLAD clusters; "
                "use more images, a larger input_size or fewer model.clusters"
            )
        local = local[self.rng.permutation(len(local))[: train.kmeans_samples]]
        kmeans = faiss.Kmeans(local.shape[1], clusters, niter=25, seed=int(self.config.runtime.seed), verbose=False)
        kmeans.train(local)
        alpha = self.network.vlad.initialise(kmeans.centroids.astype(np.float32), local)
        self.log(f"NetVLAD: {clusters} clusters from k-means on {len(local)} local features, alpha {alpha:.1f}")
        self.network.train()

    def state(self) -> dict:
        return {
            "numpy_rng": numpy_rng_state(self.rng),
            "cache_step": self.cache_step,
            "cache": {c: torch.from_numpy(v) for c, v in self.cache.items()},
        }

    def load_state(self, state: dict) -> None:
        set_numpy_rng_state(self.rng, state["numpy_rng"])
        self.cache_step = int(state.get("cache_step", -1))
        self.cache = {c: v.numpy() for c, v in state.get("cache", {}).items()}

    def before_save(self) -> None:
        if self.config.model.pca_dim:
            was_training = self.network.training
            self.network.eval()
            self.network.fit_pca(self._describe_maps(self.all_maps))
            self.network.train(was_training)

    def validation_vectors(self, images: torch.Tensor) -> np.ndarray:
        maps = self._trunk_maps(images)
        was_training = self.network.training
        self.network.eval()
        with torch.inference_mode():
            out = self.network(maps).float()
        self.network.train(was_training)
        return torch.nn.functional.normalize(out, dim=1).cpu().numpy()

    def train_step(self, step: int) -> dict[str, float]:
        train = self.config.train
        if self.cache_step < 0 or step - self.cache_step >= train.cache_refresh:
            self.network.eval()
            self.cache = {c: self._describe_maps(self.maps[c]) for c in self.conditions}
            self.cache_step = step
        self.network.train()
        cache, maps, conditions = self.cache, self.maps, self.conditions
        q_maps, p_maps, n_maps = [], [], []
        for _ in range(train.batch_size):
            q_cond, d_cond = self.rng.choice(len(conditions), size=2, replace=False)
            q_cond, d_cond = conditions[q_cond], conditions[d_cond]
            i = int(self.rng.integers(len(self.frame_ids)))
            query = cache[q_cond][i]
            # best-matching potential positive (weak supervision: the nearest one in descriptor space)
            positives = self.positives[i]
            pos = positives[np.argmin(((cache[d_cond][positives] - query) ** 2).sum(1))]
            pool = self.negatives[i]
            if len(pool) > train.negatives_sampled:
                pool = self.rng.choice(pool, size=train.negatives_sampled, replace=False)
            dist = ((cache[d_cond][pool] - query) ** 2).sum(1)
            hardest = pool[np.argsort(dist, kind="stable")[: train.hard_negatives]]
            if len(hardest) < train.hard_negatives:  # fewer negatives than asked: repeat the hardest
                hardest = np.resize(hardest, train.hard_negatives)
            q_maps.append(maps[q_cond][i])
            p_maps.append(maps[d_cond][pos])
            n_maps.extend(maps[d_cond][j] for j in hardest)
        batch = torch.stack(q_maps + p_maps + n_maps)
        vectors = self.network.vlad_vectors(batch).float()
        b = train.batch_size
        q, p = vectors[:b], vectors[b : 2 * b]
        n = vectors[2 * b :].view(b, train.hard_negatives, -1)
        d_pos = ((q - p) ** 2).sum(1, keepdim=True)
        d_neg = ((q[:, None, :] - n) ** 2).sum(2)
        hinge = torch.relu(d_pos - d_neg + train.margin)
        loss = hinge.mean()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        # False when the loss is not finite here or on another rank: every rank stops at this step
        if not self.distributed.average_gradients(self.optimizer, loss):
            raise FloatingPointError(f"NetVLAD loss became {loss_text(loss)} at step {step}; lower optim.lr")
        self.optimizer.step()
        return {"loss": float(loss.item()), "active_triplets": float((hinge > 0).float().mean().item())}


def train(
    config: NetVLADRunConfig,
    run_dir,
    resume: bool = False,
    override: bool = False,
    max_minutes: float | None = None,
    progress: bool = True,
    command: str = "fdnet train netvlad",
) -> dict:
    """Train NetVLAD as ``config`` says into ``run_dir`` (what ``fdnet train netvlad`` calls)."""
    from fdnet.training.data import load_validation_images
    from fdnet.training.loop import run_training

    validate(config)

    def build():
        data = route_images(training_route(config.data), config.model.input_size, min_conditions=2, why="NetVLAD")
        validation = load_validation_images(config.data.root, config.validation, config.model.input_size)
        return NetVLADTraining(config, data), validation

    return run_training(
        build,
        run_dir,
        resume=resume,
        override=override,
        max_minutes=max_minutes,
        progress=progress,
        command=command,
        runtime=config.runtime,
    )
