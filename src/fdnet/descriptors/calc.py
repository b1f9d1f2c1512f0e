"""CALC: a convolutional auto-encoder that learns to reconstruct HOG, trained without labels.

Source: N. Merrill and G. Huang, "Lightweight Unsupervised Deep Loop Closure", RSS 2018;
reference implementation github.com/rpng/calc (``TrainAndTest/makeNet.py`` for the network,
``TrainAndTest/writeDatabase.py`` for the training pairs).

What the original does, and this module reproduces:

* input: one grey image resized to 120x160 (H x W), scaled to [0, 1];
* training pair: the image and a random *projective* warp of it that only zooms in (each corner
  of the source quadrilateral is drawn uniformly from the outer quarter of its own corner of the
  image, then mapped onto the full frame: perspective change + crop); one of the two is the
  network's input and the target is the HOG descriptor of the *other* (which one is random, 50/50,
  "since we can only zoom in");
* HOG target: OpenCV ``HOGDescriptor(winSize=(16, 32), blockSize=(16, 16), blockStride=(16, 16),
  cellSize=(8, 8), nbins=2)`` computed densely over the 160x120 image (window stride 8x8), which
  gives 3648 values;
* encoder: conv 5x5/2 (pad 4) 64 ch, ReLU, max-pool 3/2, LRN(5, 1e-4, 0.75); conv 4x4 (pad 2)
  128 ch, ReLU, max-pool 3/2, LRN; conv 3x3 4 ch, ReLU -> 4x14x19 = 1064 values, which flattened
  *is the descriptor*; Caffe pools with ceil rounding, so ``ceil_mode=True`` here;
* decoder (training only): fully connected 1064 -> 1064 -> 2048 -> 3648, each followed by a
  sigmoid; loss: Caffe's EuclideanLoss, sum of squared errors / (2 * batch);
* images compared by cosine similarity of the descriptors.

Where this implementation differs (all are settings in :class:`CALCTrainConfig` /
:class:`CALCModelConfig`):

* training budget: the original ran ~43 epochs (its code's setting) over a large scene-image
  corpus on GPUs; here a run lasts minutes on a CPU, on whatever images the user gives. The
  default optimiser is Adam (lr 1e-3, batch 32) rather than the original's SGD (lr 9e-4,
  momentum 0.9, weight decay 5e-4, batch 256), because it adapts its step sizes, which matters
  in runs of minutes (the two were not compared here); ``optimizer: sgd`` restores the SGD;
* initialisation: the original draws every weight and bias from N(0, 0.01). With that and
  Adam, every bottleneck ReLU died within ~40 steps in our runs (all descriptors exactly zero,
  retrieval at chance), and with N(0, 0.01) decoder weights the gradient reaching the encoder was
  so small that it stayed at its initial weights (max change 1e-6 over 290 steps). So by default
  the convolutions are He-initialised with zero biases, the decoder's layers Xavier-initialised,
  and the output bias starts at the training set's mean HOG (``model.init: original`` and
  ``train.init_output_bias: false`` restore the original); training logs the share of active
  bottleneck units and warns when it reaches zero;
* warps are drawn afresh at every step (the original wrote one fixed warp per image into an
  LMDB), so a small training set still gives varied pairs; the HOG of each *original* image is
  computed once up front, the HOG of a warp only when the swap puts the original at the input;
* ``describe`` runs under bfloat16 autocast on CPUs with native bf16 (about twice as fast as
  float32 here);
* ``small`` preset (not the original network): 60x80 input and 32/64/4 channels, ~14x cheaper.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.errors import ConfigError
from fdnet.training.baselines import TrainingDataConfig, load_method_config

METHOD = "calc"


@dataclass
class HOGTargetConfig:
    """OpenCV HOGDescriptor settings of the reconstruction target, (width, height) as OpenCV
    takes them. Defaults are the original's (3648 values for a 160x120 image)."""

    win_size: tuple[int, int] = (16, 32)
    block_size: tuple[int, int] = (16, 16)
    block_stride: tuple[int, int] = (16, 16)
    cell_size: tuple[int, int] = (8, 8)
    nbins: int = 2
    #: stride of the dense window grid (OpenCV's default for ``compute`` is the cell size)
    win_stride: tuple[int, int] = (8, 8)


@dataclass
class CALCModelConfig:
    #: (height, width) of the grey input; the original's is 120x160
    input_size: tuple[int, int] = (120, 160)
    #: output channels of conv1, conv2 and conv3 (the bottleneck)
    channels: tuple[int, int, int] = (64, 128, 4)
    #: hidden fully connected layers of the decoder; the output layer has the HOG length.
    #: Empty list = the original's (first hidden layer as long as the descriptor, then 2048).
    decoder_hidden: list[int] = field(default_factory=list)
    hog: HOGTargetConfig = field(default_factory=HOGTargetConfig)
    #: "he": He-normal convolutions with zero biases; "original": every weight and bias N(0, 0.01)
    #: as in the reference code, which with Adam let all bottleneck ReLUs die within a few dozen
    #: steps here (every descriptor all-zero)
    init: str = "he"


@dataclass
class CALCTrainConfig:
    #: the original used 256 on GPUs; 32 keeps CPU steps short (the step time scales with it)
    batch_size: int = 32
    steps: int = 600
    #: "adam" (default, fast in short runs) or "sgd" (the original's: lr 9e-4, momentum 0.9)
    optimizer: str = "adam"
    lr: float = 1e-3
    momentum: float = 0.9
    weight_decay: float = 5e-4
    #: start the decoder's output bias at the training set's mean HOG (not in the original)
    init_output_bias: bool = True
    #: probability that the original (not the warp) is the input and the warp's HOG the target
    swap_probability: float = 0.5
    #: bfloat16 autocast for the training forward pass (when the CPU supports it natively); off by
    #: default: on this network it made training steps slower, not faster (measured on 2 cores)
    bf16: bool = False
    seed: int = 0
    checkpoint_every: int = 250
    log_every: int = 50


@dataclass
class CALCRunConfig:
    method: str = METHOD
    model: CALCModelConfig = field(default_factory=CALCModelConfig)
    train: CALCTrainConfig = field(default_factory=CALCTrainConfig)
    data: TrainingDataConfig = field(default_factory=TrainingDataConfig)


def tiny_config() -> CALCRunConfig:
    """A few-second setting for tests: 60x80 input, narrow layers, small decoder."""
    config = CALCRunConfig()
    config.model = dataclasses.replace(config.model, input_size=(60, 80), channels=(8, 16, 4),
                                       decoder_hidden=[128])
    config.train = dataclasses.replace(config.train, batch_size=8, steps=20, checkpoint_every=10,
                                       log_every=5)
    return config


def small_config() -> CALCRunConfig:
    """Not the original's network: half-resolution input (60x80) and half-width convolutions
    (32, 64, 4 channels -> a 216-d descriptor, HOG target 576-d), about 14x cheaper per image, so
    a CPU run of minutes sees many more warped pairs."""
    config = CALCRunConfig()
    config.model = dataclasses.replace(config.model, input_size=(60, 80), channels=(32, 64, 4))
    return config


PRESETS = {"default": CALCRunConfig, "small": small_config, "tiny": tiny_config}


# ----------------------------------------------------------------------------- HOG and warps
def hog_descriptor(config: HOGTargetConfig):
    import cv2

    return cv2.HOGDescriptor(tuple(config.win_size), tuple(config.block_size), tuple(config.block_stride),
                             tuple(config.cell_size), int(config.nbins))


def hog_length(model: CALCModelConfig) -> int:
    height, width = model.input_size
    return int(compute_hog(np.zeros((1, height, width), np.uint8), model.hog).shape[1])


def compute_hog(images_u8: np.ndarray, config: HOGTargetConfig, hog=None) -> np.ndarray:
    """(N, H, W) uint8 grey -> (N, D) float32 HOG targets (OpenCV, dense windows)."""
    hog = hog or hog_descriptor(config)
    height, width = images_u8.shape[1:3]
    win_w, win_h = config.win_size
    if width < win_w or height < win_h:
        raise ConfigError(f"CALC HOG window {win_w}x{win_h} (WxH) does not fit the {width}x{height} input")
    out = [np.asarray(hog.compute(np.ascontiguousarray(im), tuple(config.win_stride)), np.float32).ravel()
           for im in images_u8]
    return np.stack(out) if out else np.zeros((0, 0), np.float32)


def random_perspective_warp(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Zoom-in projective warp of a (H, W) image, as CALC's ``randPerspectiveWarp``: each corner of
    a quadrilateral is drawn from the outer quarter of its own image corner and stretched onto the
    full frame (so no invented border pixels appear)."""
    import cv2

    height, width = image.shape[:2]
    qx, qy = width / 4.0, height / 4.0
    corners = np.array([[0, 0], [0, height], [width, 0], [width, height]], np.float32)
    low_x = np.array([0, 0, 3 * qx, 3 * qx]); low_y = np.array([0, 3 * qy, 0, 3 * qy])
    source = np.stack([low_x + rng.uniform(0, qx, 4), low_y + rng.uniform(0, qy, 4)], axis=1).astype(np.float32)
    transform = cv2.getPerspectiveTransform(source, corners)
    return cv2.warpPerspective(image, transform, (width, height))


def to_grey_u8(images: np.ndarray) -> np.ndarray:
    """(N, H, W, 3) float RGB in [0, 1] -> (N, H, W) uint8 luminance."""
    from fdnet.data.images import to_grey

    return np.clip(np.rint(to_grey(np.asarray(images, np.float32)) * 255.0), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------- network
def build_network(config: CALCModelConfig):
    """The CALC auto-encoder as a ``torch.nn.Module`` with ``encode`` (descriptor) and
    ``forward`` (HOG reconstruction)."""
    import torch
    from torch import nn

    class CALCNet(nn.Module):
        def __init__(self, model: CALCModelConfig):
            super().__init__()
            c1, c2, c3 = (int(c) for c in model.channels)
            self.encoder = nn.Sequential(
                nn.Conv2d(1, c1, 5, stride=2, padding=4), nn.ReLU(inplace=True),
                nn.MaxPool2d(3, stride=2, ceil_mode=True), nn.LocalResponseNorm(5, alpha=1e-4, beta=0.75),
                nn.Conv2d(c1, c2, 4, padding=2), nn.ReLU(inplace=True),
                nn.MaxPool2d(3, stride=2, ceil_mode=True), nn.LocalResponseNorm(5, alpha=1e-4, beta=0.75),
                nn.Conv2d(c2, c3, 3), nn.ReLU(inplace=True),
            )
            height, width = model.input_size
            with torch.no_grad():
                self.descriptor_dim = int(self.encoder(torch.zeros(1, 1, height, width)).numel())
            if self.descriptor_dim <= 0:
                raise ConfigError(f"CALC input size {height}x{width} is too small for its encoder")
            hidden = list(model.decoder_hidden) or [self.descriptor_dim, 2048]
            sizes = [self.descriptor_dim] + [int(h) for h in hidden] + [hog_length(model)]
            layers: list[nn.Module] = []
            for a, b in zip(sizes[:-1], sizes[1:]):
                layers += [nn.Linear(a, b), nn.Sigmoid()]
            self.decoder = nn.Sequential(*layers)
            for module in self.modules():
                if isinstance(module, (nn.Conv2d, nn.Linear)):
                    if model.init == "original":
                        nn.init.normal_(module.weight, 0.0, 0.01)
                        nn.init.normal_(module.bias, 0.0, 0.01)
                    elif model.init == "he" and isinstance(module, nn.Conv2d):
                        # He init keeps conv activations input-driven rather than bias-driven, so the
                        # 4-channel bottleneck's ReLUs do not all die in the first steps
                        nn.init.kaiming_normal_(module.weight, nonlinearity="relu")
                        nn.init.zeros_(module.bias)
                    elif model.init == "he":
                        # Xavier for the sigmoid decoder: with N(0, 0.01) the gradient reaching the
                        # encoder through three sigmoid layers was so small the encoder never moved
                        nn.init.xavier_uniform_(module.weight)
                        nn.init.zeros_(module.bias)
                    else:
                        raise ConfigError(f"CALC model.init: {model.init!r} is not one of he, original")

        def encode(self, x):
            return self.encoder(x).flatten(1)

        def forward(self, x):
            return self.decoder(self.encode(x))

    return CALCNet(config)


def euclidean_loss(prediction, target):
    """Caffe's EuclideanLoss: sum of squared differences / (2 * batch)."""
    return ((prediction - target) ** 2).sum() / (2 * prediction.shape[0])


# ----------------------------------------------------------------------------- checkpoints
def load_run_config(run_dir: str | Path) -> CALCRunConfig:
    """Read a CALC run's config, with a clear error for anything that is not a CALC run."""
    return load_method_config(run_dir, CALCRunConfig, METHOD)


class CALCDescriptor(Descriptor):
    """CALC bottleneck (conv3 output, flattened), L2-normalised, compared by cosine.

    ``checkpoint``: a run directory written by ``fdnet train-baseline calc``. ``bf16``: autocast
    (default: on where the CPU has native bf16). ``threads``: torch threads while describing.
    """

    name = "calc"

    def __init__(self, checkpoint: str | Path | None = None, bf16: bool | None = None,
                 threads: int | None = None):
        import torch

        from fdnet.descriptors.backbone import bf16_supported
        from fdnet.training.checkpoint import load_weights

        if checkpoint is None:
            raise ConfigError("method 'calc' needs a trained model: --checkpoint RUN_DIR "
                              "(train one with `fdnet train-baseline calc --data DIR --out RUN_DIR`)")
        self.checkpoint = Path(checkpoint)
        self.config = load_run_config(self.checkpoint)
        self.input_size = tuple(int(v) for v in self.config.model.input_size)
        self.network = build_network(self.config.model).eval()
        metadata = load_weights(self.checkpoint, {"calc": self.network})
        self.step = int(metadata.get("step", 0))
        self.bf16 = bf16_supported() if bf16 is None else bool(bf16)
        self.threads = threads
        self._torch = torch

    @property
    def dim(self) -> int:
        return self.network.descriptor_dim

    def describe(self, images: np.ndarray) -> np.ndarray:
        from fdnet.descriptors.backbone import torch_threads

        torch = self._torch
        grey = to_grey_u8(images).astype(np.float32) / 255.0
        x = torch.from_numpy(np.ascontiguousarray(grey))[:, None]
        if x.shape[-2:] != self.input_size:
            raise ConfigError(f"CALC expects images of size {self.input_size}, got {tuple(x.shape[-2:])}")
        with torch_threads(self.threads), torch.inference_mode():
            if self.bf16:
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    out = self.network.encode(x.contiguous(memory_format=torch.channels_last))
            else:
                out = self.network.encode(x)
        return l2_normalize(out.float().numpy())

    def settings(self) -> dict:
        return {"input_size": list(self.input_size), "checkpoint": str(self.checkpoint), "step": self.step,
                "dim": self.dim, "bf16": self.bf16}
