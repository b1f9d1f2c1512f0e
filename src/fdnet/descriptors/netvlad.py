"""NetVLAD: a trainable VLAD pooling layer on a pretrained CNN, learned from weak place supervision.

Source: R. Arandjelović, P. Gronat, A. Torii, T. Pajdla, J. Sivic, "NetVLAD: CNN architecture for
weakly supervised place recognition", CVPR 2016; the PyTorch port github.com/Nanne/pytorch-NetVlad
(which the FDNet paper used, "with the hardest triplet loss").

The layer, as in the original (``vladv1`` of the port): local features are L2-normalised; a 1x1
convolution gives soft-assignment scores to K clusters, softmax over clusters; the residuals to
each cluster centre are summed with those weights; each cluster's residual vector is
L2-normalised (intra-normalisation), the K x C result flattened and L2-normalised. Centres are
initialised by k-means (faiss) on L2-normalised local features of training images, the
assignment weights as ``alpha * centre / |centre|`` with ``alpha = -log(0.01) / mean(top-1 minus
top-2 dot product)``, as the port does. Training is a triplet ranking loss with the original's
margin m = 0.1 on *squared* Euclidean distances: for each query, the best-matching potential
positive (nearest in descriptor space among the references within the ground-truth tolerance)
against the hardest negative(s) among negatives sampled from references farther than
``negative_distance`` frames; descriptors used for mining come from a cache recomputed every
``cache_refresh`` steps, as the port does. Queries and references come from *different*
conditions of the training split. Optional PCA + whitening to ``pca_dim`` (fitted on the training
descriptors, then L2 normalisation), as the original's dimensionality reduction.

Where this implementation differs (each a setting in :class:`NetVLADModelConfig` /
:class:`NetVLADTrainConfig`):

* backbone: EfficientNet-Lite0 ImageNet weights (the only pretrained weights available here;
  see :mod:`fdnet.descriptors.backbone`) instead of VGG-16. The trunk up to ``frozen_block``
  (default 9) is frozen and its maps are computed once per training image, which is what makes
  CPU training take minutes; blocks ``frozen_block+1 .. last_block`` (default: block 10 only,
  the last block of the 112-channel stride-16 stage) are fine-tuned with the NetVLAD layer, as
  the original fine-tunes VGG's last conv layers only (conv5_1-3). Fine-tuning the whole
  112-channel stage (``frozen_block: 7``) took about 15 s per 8-triplet step in our runs against
  about 1 s for block 10 alone (on a shared 2-core machine whose load differed between the two
  runs, so the ratio is indicative only). BatchNorm statistics of the
  fine-tuned blocks stay frozen (batches of a few triplets are too small to estimate them);
* clusters: 64 (the original's) x 112 channels = 7168-d, no PCA by default (the original reduced
  32768-d to 4096 with PCA + whitening; ``pca_dim`` does that here, and needs at least that many
  training images);
* the default optimiser is Adam with lr 1e-4 (one of the port's options); training lasts minutes
  on the user's own route instead of days on Pittsburgh 250k; one hardest negative per query by
  default (the port uses the 10 hardest of 1000 samples; ``hard_negatives`` sets it);
* input size defaults to 180x320 (16:9) and ``describe`` runs under bfloat16 autocast on CPUs
  with native bf16.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.errors import ConfigError
from fdnet.training.baselines import TrainingDataConfig, load_method_config

METHOD = "netvlad"


@dataclass
class NetVLADModelConfig:
    #: (height, width) images are resized to
    input_size: tuple[int, int] = (180, 320)
    #: EfficientNet-Lite0 blocks 0..frozen_block are frozen (their maps are cached in training)
    frozen_block: int = 9
    #: blocks frozen_block+1..last_block are fine-tuned (none when equal: only the NetVLAD layer
    #: learns); NetVLAD pools the output of last_block
    last_block: int = 10
    #: number of VLAD clusters K (descriptor length K x channels of last_block before PCA)
    clusters: int = 64
    #: PCA + whitening to this length after training (0 = off)
    pca_dim: int = 0


@dataclass
class NetVLADTrainConfig:
    #: queries (triplets) per step
    batch_size: int = 8
    steps: int = 600
    #: "adam" or "sgd" (momentum, weight_decay apply to sgd)
    optimizer: str = "adam"
    lr: float = 1e-4
    momentum: float = 0.9
    weight_decay: float = 1e-3
    #: triplet margin on squared L2 distances between unit vectors (the original's m = 0.1)
    margin: float = 0.1
    #: references more than this many frames from the query are negatives (positives: within
    #: data.tolerance); frames in between are neither
    negative_distance: int = 10
    #: negatives sampled per query before picking the hardest (the port's 1000)
    negatives_sampled: int = 1000
    #: hardest negatives used per query
    hard_negatives: int = 1
    #: steps between recomputing every training descriptor for mining
    cache_refresh: int = 100
    #: local features sampled for the k-means initialisation of the clusters
    kmeans_samples: int = 50000
    #: bfloat16 autocast for the frozen trunk and the mining cache (no gradients there)
    bf16: bool = True
    seed: int = 0
    checkpoint_every: int = 200
    log_every: int = 20


@dataclass
class NetVLADRunConfig:
    method: str = METHOD
    model: NetVLADModelConfig = field(default_factory=NetVLADModelConfig)
    train: NetVLADTrainConfig = field(default_factory=NetVLADTrainConfig)
    data: TrainingDataConfig = field(default_factory=TrainingDataConfig)


def tiny_config() -> NetVLADRunConfig:
    """A few-second setting for tests: small input, 8 clusters, one fine-tuned block."""
    config = NetVLADRunConfig()
    config.model = dataclasses.replace(config.model, input_size=(64, 112), frozen_block=7, last_block=8,
                                       clusters=8)
    config.train = dataclasses.replace(config.train, batch_size=4, steps=6, negatives_sampled=50,
                                       cache_refresh=3, kmeans_samples=2000, checkpoint_every=3,
                                       log_every=2, negative_distance=4)
    return config


PRESETS = {"default": NetVLADRunConfig, "tiny": tiny_config}


def check_model_config(model: NetVLADModelConfig) -> None:
    from fdnet.descriptors.backbone import NUM_BLOCKS, check_block

    check_block(model.frozen_block)
    check_block(model.last_block)
    if not model.frozen_block <= model.last_block < NUM_BLOCKS:
        raise ConfigError(f"NetVLAD needs frozen_block <= last_block (got {model.frozen_block}, "
                          f"{model.last_block}): NetVLAD pools a block at or after the frozen trunk")
    if model.clusters < 1 or model.pca_dim < 0:
        raise ConfigError("NetVLAD model.clusters must be >= 1 and model.pca_dim >= 0")


# ----------------------------------------------------------------------------- network
def build_network(model: NetVLADModelConfig, pretrained: bool = True):
    """The trainable part: the fine-tuned backbone blocks, the NetVLAD layer and (when
    ``pca_dim``) the PCA-whitening buffers. Input: the frozen trunk's maps after
    ``frozen_block``; output: (N, dim) unit vectors."""
    import torch
    from torch import nn
    from torch.nn import functional as F

    from fdnet.descriptors.backbone import BLOCK_CHANNELS, build_efficientnet_lite0

    check_model_config(model)

    class NetVLADLayer(nn.Module):
        def __init__(self, clusters: int, channels: int):
            super().__init__()
            self.assign = nn.Conv2d(channels, clusters, kernel_size=1, bias=False)
            self.centroids = nn.Parameter(torch.rand(clusters, channels))

        def initialise(self, centroids: np.ndarray, local: np.ndarray) -> float:
            """Centres from k-means, assignment weights alpha * unit centre (the port's vladv1)."""
            unit = centroids / np.linalg.norm(centroids, axis=1, keepdims=True)
            dots = np.sort(unit @ local.T, axis=0)[::-1]
            alpha = float(-np.log(0.01) / np.mean(dots[0] - dots[1]))
            with torch.no_grad():
                self.centroids.copy_(torch.from_numpy(centroids))
                self.assign.weight.copy_(torch.from_numpy(alpha * unit)[:, :, None, None])
            return alpha

        def forward(self, x):
            x = F.normalize(x, p=2, dim=1)
            soft = F.softmax(self.assign(x).flatten(2), dim=1)          # (N, K, P)
            local = x.flatten(2)                                         # (N, C, P)
            # sum_p a_kp (x_p - c_k) = (A X^T)_k - (sum_p a_kp) c_k, computed in one batched matmul
            vlad = torch.bmm(soft, local.transpose(1, 2)) - soft.sum(-1).unsqueeze(-1) * self.centroids
            vlad = F.normalize(vlad, p=2, dim=2)                          # intra-normalisation
            return F.normalize(vlad.flatten(1), p=2, dim=1)

    class NetVLADNet(nn.Module):
        def __init__(self):
            super().__init__()
            trunk = build_efficientnet_lite0(pretrained=pretrained)
            self.blocks = nn.ModuleList(trunk._blocks[model.frozen_block + 1: model.last_block + 1])
            channels = BLOCK_CHANNELS[model.last_block]
            self.vlad = NetVLADLayer(model.clusters, channels)
            self.vlad_dim = model.clusters * channels
            if model.pca_dim > self.vlad_dim:
                raise ConfigError(f"NetVLAD pca_dim {model.pca_dim} exceeds the VLAD length {self.vlad_dim}")
            if model.pca_dim:
                self.register_buffer("pca_mean", torch.zeros(self.vlad_dim))
                self.register_buffer("pca_projection", torch.zeros(model.pca_dim, self.vlad_dim))
            self.descriptor_dim = model.pca_dim or self.vlad_dim

        def local_features(self, maps):
            for block in self.blocks:
                maps = block(maps)
            return maps

        def vlad_vectors(self, maps):
            return self.vlad(self.local_features(maps))

        def forward(self, maps):
            v = self.vlad_vectors(maps)
            if model.pca_dim:
                v = F.normalize((v.float() - self.pca_mean) @ self.pca_projection.T, p=2, dim=1)
            return v

        def train(self, mode: bool = True):
            super().train(mode)
            # BatchNorm statistics of the pretrained blocks stay frozen (tiny triplet batches)
            self.blocks.eval()
            return self

        def fit_pca(self, vectors: np.ndarray) -> None:
            from sklearn.decomposition import PCA

            if len(vectors) <= model.pca_dim:
                raise ConfigError(f"NetVLAD pca_dim {model.pca_dim} needs more than {model.pca_dim} training "
                                  f"images, got {len(vectors)}")
            pca = PCA(n_components=model.pca_dim, svd_solver="randomized", random_state=0).fit(vectors)
            whitening = pca.components_ / np.sqrt(pca.explained_variance_ + 1e-9)[:, None]
            with torch.no_grad():
                self.pca_mean.copy_(torch.from_numpy(pca.mean_.astype(np.float32)))
                self.pca_projection.copy_(torch.from_numpy(whitening.astype(np.float32)))

    return NetVLADNet()


def load_run_config(run_dir: str | Path) -> NetVLADRunConfig:
    """Read a NetVLAD run's config, with a clear error for anything that is not a NetVLAD run."""
    return load_method_config(run_dir, NetVLADRunConfig, METHOD)


class NetVLADDescriptor(Descriptor):
    """NetVLAD vector (optionally PCA-whitened), L2-normalised, compared by cosine.

    ``checkpoint``: a run directory written by ``fdnet train-baseline netvlad``. The frozen trunk
    comes from the installed EfficientNet-Lite0 ImageNet weights, the fine-tuned blocks and the
    VLAD layer from the run. ``bf16``: autocast (default: on where the CPU has native bf16).
    ``threads``: torch threads while describing.
    """

    name = "netvlad"

    def __init__(self, checkpoint: str | Path | None = None, bf16: bool | None = None,
                 threads: int | None = None):
        from fdnet.descriptors.backbone import FeatureExtractor
        from fdnet.training.checkpoint import load_weights

        if checkpoint is None:
            raise ConfigError("method 'netvlad' needs a trained model: --checkpoint RUN_DIR "
                              "(train one with `fdnet train-baseline netvlad --data DIR --out RUN_DIR`)")
        self.checkpoint = Path(checkpoint)
        self.config = load_run_config(self.checkpoint)
        model = self.config.model
        self.input_size = tuple(int(v) for v in model.input_size)
        # pretrained=False: every fine-tuned weight comes from the checkpoint
        self.network = build_network(model, pretrained=False).eval()
        metadata = load_weights(self.checkpoint, {"netvlad": self.network})
        self.step = int(metadata.get("step", 0))
        self.extractor = FeatureExtractor(block=model.frozen_block, bf16=bf16, threads=threads)
        self.bf16 = self.extractor.bf16
        self.threads = threads

    @property
    def dim(self) -> int:
        return self.network.descriptor_dim

    def describe(self, images: np.ndarray) -> np.ndarray:
        import torch

        from fdnet.descriptors.backbone import torch_threads

        images = np.asarray(images, dtype=np.float32)
        if images.shape[1:3] != self.input_size:
            raise ConfigError(f"NetVLAD expects images of size {self.input_size}, got {images.shape[1:3]}")
        maps = self.extractor.features_tensor(images)
        with torch_threads(self.threads), torch.inference_mode():
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.bf16):
                out = self.network(maps.contiguous(memory_format=torch.channels_last) if self.bf16 else maps)
        return l2_normalize(out.float().numpy())

    def settings(self) -> dict:
        model = self.config.model
        return {"input_size": list(self.input_size), "checkpoint": str(self.checkpoint), "step": self.step,
                "dim": self.dim, "clusters": model.clusters, "frozen_block": model.frozen_block,
                "last_block": model.last_block, "pca_dim": model.pca_dim, "bf16": self.bf16}
