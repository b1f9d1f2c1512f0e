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
  see :mod:`fdnet.backbones`) instead of VGG-16. The trunk up to ``frozen_block``
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

import numpy as np

from fdnet.errors import ConfigError
from fdnet.methods.netvlad.config import NetVLADModelConfig


def check_model_config(model: NetVLADModelConfig) -> None:
    from fdnet.backbones import NUM_BLOCKS, check_block

    check_block(model.frozen_block)
    check_block(model.last_block)
    if not model.frozen_block <= model.last_block < NUM_BLOCKS:
        raise ConfigError(
            f"NetVLAD needs frozen_block <= last_block (got {model.frozen_block}, "
            f"{model.last_block}): NetVLAD pools a block at or after the frozen trunk"
        )
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

    from fdnet.backbones import BLOCK_CHANNELS, build_efficientnet_lite0

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
            soft = F.softmax(self.assign(x).flatten(2), dim=1)  # (N, K, P)
            local = x.flatten(2)  # (N, C, P)
            # sum_p a_kp (x_p - c_k) = (A X^T)_k - (sum_p a_kp) c_k, computed in one batched matmul
            vlad = torch.bmm(soft, local.transpose(1, 2)) - soft.sum(-1).unsqueeze(-1) * self.centroids
            vlad = F.normalize(vlad, p=2, dim=2)  # intra-normalisation
            return F.normalize(vlad.flatten(1), p=2, dim=1)

    class NetVLADNet(nn.Module):
        def __init__(self):
            super().__init__()
            trunk = build_efficientnet_lite0(pretrained=pretrained)
            self.blocks = nn.ModuleList(trunk._blocks[model.frozen_block + 1 : model.last_block + 1])
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
                raise ConfigError(
                    f"NetVLAD pca_dim {model.pca_dim} needs more than {model.pca_dim} training "
                    f"images, got {len(vectors)}"
                )
            pca = PCA(n_components=model.pca_dim, svd_solver="randomized", random_state=0).fit(vectors)
            whitening = pca.components_ / np.sqrt(pca.explained_variance_ + 1e-9)[:, None]
            with torch.no_grad():
                self.pca_mean.copy_(torch.from_numpy(pca.mean_.astype(np.float32)))
                self.pca_projection.copy_(torch.from_numpy(whitening.astype(np.float32)))

    return NetVLADNet()
