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

import numpy as np

from fdnet.errors import ConfigError
from fdnet.methods.calc.config import CALCModelConfig, HOGTargetConfig


# ----------------------------------------------------------------------------- HOG and warps
def hog_descriptor(config: HOGTargetConfig):
    import cv2

    from fdnet.descriptors.classic import check_opencv_hog

    check_opencv_hog(
        config.win_size, config.block_size, config.block_stride, config.cell_size, config.nbins, "calc: model.hog"
    )
    return cv2.HOGDescriptor(
        tuple(config.win_size),
        tuple(config.block_size),
        tuple(config.block_stride),
        tuple(config.cell_size),
        int(config.nbins),
    )


def hog_length(model: CALCModelConfig) -> int:
    from fdnet.data.images import check_image_size

    height, width = check_image_size(model.input_size, "calc: model.input_size")
    return int(compute_hog(np.zeros((1, height, width), np.uint8), model.hog).shape[1])


def compute_hog(images_u8: np.ndarray, config: HOGTargetConfig, hog=None) -> np.ndarray:
    """(N, H, W) uint8 grey -> (N, D) float32 HOG targets (OpenCV, dense windows)."""
    hog = hog or hog_descriptor(config)
    height, width = images_u8.shape[1:3]
    win_w, win_h = config.win_size
    if width < win_w or height < win_h:
        raise ConfigError(f"CALC HOG window {win_w}x{win_h} (WxH) does not fit the {width}x{height} input")
    out = [
        np.asarray(hog.compute(np.ascontiguousarray(im), tuple(config.win_stride)), np.float32).ravel()
        for im in images_u8
    ]
    return np.stack(out) if out else np.zeros((0, 0), np.float32)


def random_perspective_warp(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Zoom-in projective warp of a (H, W) image, as CALC's ``randPerspectiveWarp``: each corner of
    a quadrilateral is drawn from the outer quarter of its own image corner and stretched onto the
    full frame (so no invented border pixels appear)."""
    import cv2

    height, width = image.shape[:2]
    qx, qy = width / 4.0, height / 4.0
    corners = np.array([[0, 0], [0, height], [width, 0], [width, height]], np.float32)
    low_x = np.array([0, 0, 3 * qx, 3 * qx])
    low_y = np.array([0, 3 * qy, 0, 3 * qy])
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
                nn.Conv2d(1, c1, 5, stride=2, padding=4),
                nn.ReLU(inplace=True),
                nn.MaxPool2d(3, stride=2, ceil_mode=True),
                nn.LocalResponseNorm(5, alpha=1e-4, beta=0.75),
                nn.Conv2d(c1, c2, 4, padding=2),
                nn.ReLU(inplace=True),
                nn.MaxPool2d(3, stride=2, ceil_mode=True),
                nn.LocalResponseNorm(5, alpha=1e-4, beta=0.75),
                nn.Conv2d(c2, c3, 3),
                nn.ReLU(inplace=True),
            )
            hog_size = hog_length(model)  # checks the input size and the HOG settings first
            height, width = model.input_size
            try:
                with torch.no_grad():
                    self.descriptor_dim = int(self.encoder(torch.zeros(1, 1, height, width)).numel())
            except RuntimeError:  # torch's words for a map that shrank to nothing
                self.descriptor_dim = 0
            if self.descriptor_dim <= 0:
                raise ConfigError(f"CALC input size {height}x{width} is too small for its encoder")
            hidden = list(model.decoder_hidden) or [self.descriptor_dim, 2048]
            sizes = [self.descriptor_dim] + [int(h) for h in hidden] + [hog_size]
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
