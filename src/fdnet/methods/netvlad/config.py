"""NetVLAD run configuration: model, training and data settings, presets (see
:mod:`fdnet.methods.netvlad.model` for the method and where it differs from the original)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from fdnet.methods.settings import DataConfig, OptimizerConfig, RuntimeConfig, StepsInTrainSection, ValidationConfig

METHOD = "netvlad"


@dataclass
class NetVLADDataConfig(DataConfig):
    #: frame tolerance of the training split's frame-aligned ground truth (NetVLAD's positives)
    tolerance: int = 0


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


def _optim() -> OptimizerConfig:
    return OptimizerConfig(optimizer="adam", lr=1e-4, momentum=0.9, weight_decay=1e-3)


def _runtime() -> RuntimeConfig:
    # bf16: autocast for the frozen trunk and the mining cache (no gradients there), where the
    # device runs bf16 natively
    return RuntimeConfig(bf16=True, checkpoint_every=200, log_every=20)


@dataclass
class NetVLADRunConfig(StepsInTrainSection):
    method: str = METHOD
    #: the preset the run started from ("" for a config built without one)
    preset: str = ""
    model: NetVLADModelConfig = field(default_factory=NetVLADModelConfig)
    train: NetVLADTrainConfig = field(default_factory=NetVLADTrainConfig)
    optim: OptimizerConfig = field(default_factory=_optim)
    runtime: RuntimeConfig = field(default_factory=_runtime)
    data: NetVLADDataConfig = field(default_factory=NetVLADDataConfig)
    validation: ValidationConfig = field(default_factory=ValidationConfig)


def default_config() -> NetVLADRunConfig:
    return NetVLADRunConfig(preset="default")


def tiny_config() -> NetVLADRunConfig:
    """A few-second setting for tests: small input, 8 clusters, one fine-tuned block."""
    config = NetVLADRunConfig(preset="tiny")
    config.model = dataclasses.replace(config.model, input_size=(64, 112), frozen_block=7, last_block=8, clusters=8)
    config.train = dataclasses.replace(
        config.train,
        batch_size=4,
        steps=6,
        negatives_sampled=50,
        cache_refresh=3,
        kmeans_samples=2000,
        negative_distance=4,
    )
    config.runtime = dataclasses.replace(config.runtime, checkpoint_every=3, log_every=2)
    return config


PRESETS = {"default": default_config, "tiny": tiny_config}


def load_run_config(run_dir: str | Path) -> NetVLADRunConfig:
    """Read a NetVLAD run's config, with a clear error for anything that is not a NetVLAD run."""
    from fdnet.methods import load_method_config

    return load_method_config(run_dir, NetVLADRunConfig, METHOD)
