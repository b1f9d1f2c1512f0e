"""CALC run configuration: model, training and data settings, presets (see
:mod:`fdnet.methods.calc.model` for the method and where it differs from the original)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from fdnet.methods.settings import DataConfig, OptimizerConfig, RuntimeConfig, StepsInTrainSection, ValidationConfig

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
    #: start the decoder's output bias at the training set's mean HOG (not in the original)
    init_output_bias: bool = True
    #: probability that the original (not the warp) is the input and the warp's HOG the target
    swap_probability: float = 0.5


def _optim() -> OptimizerConfig:
    #: "adam" (default, fast in short runs) or "sgd" (the original's: lr 9e-4, momentum 0.9)
    return OptimizerConfig(optimizer="adam", lr=1e-3, momentum=0.9, weight_decay=5e-4)


def _runtime() -> RuntimeConfig:
    # bf16 off by default: on this network it made CPU training steps slower, not faster (measured
    # on 2 cores); it applies where the device runs bf16 natively
    return RuntimeConfig(bf16=False, checkpoint_every=250, log_every=50)


@dataclass
class CALCRunConfig(StepsInTrainSection):
    method: str = METHOD
    #: the preset the run started from ("" for a config built without one)
    preset: str = ""
    model: CALCModelConfig = field(default_factory=CALCModelConfig)
    train: CALCTrainConfig = field(default_factory=CALCTrainConfig)
    optim: OptimizerConfig = field(default_factory=_optim)
    runtime: RuntimeConfig = field(default_factory=_runtime)
    data: DataConfig = field(default_factory=DataConfig)
    validation: ValidationConfig = field(default_factory=ValidationConfig)


def default_config() -> CALCRunConfig:
    """The original's network (120x160 grey input, 64/128/4 channels)."""
    return CALCRunConfig(preset="default")


def tiny_config() -> CALCRunConfig:
    """A few-second setting for tests: 60x80 input, narrow layers, small decoder."""
    config = CALCRunConfig(preset="tiny")
    config.model = dataclasses.replace(config.model, input_size=(60, 80), channels=(8, 16, 4), decoder_hidden=[128])
    config.train = dataclasses.replace(config.train, batch_size=8, steps=20)
    config.runtime = dataclasses.replace(config.runtime, checkpoint_every=10, log_every=5)
    return config


def small_config() -> CALCRunConfig:
    """Not the original's network: half-resolution input (60x80) and half-width convolutions
    (32, 64, 4 channels -> a 216-d descriptor, HOG target 576-d), about 14x cheaper per image, so
    a CPU run of minutes sees many more warped pairs."""
    config = CALCRunConfig(preset="small")
    config.model = dataclasses.replace(config.model, input_size=(60, 80), channels=(32, 64, 4))
    return config


PRESETS = {"default": default_config, "small": small_config, "tiny": tiny_config}


def load_run_config(run_dir: str | Path) -> CALCRunConfig:
    """Read a CALC run's config, with a clear error for anything that is not a CALC run."""
    from fdnet.methods import load_method_config

    return load_method_config(run_dir, CALCRunConfig, METHOD)
