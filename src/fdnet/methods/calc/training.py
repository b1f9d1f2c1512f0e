"""CALC's training step on the shared loop: a random projective warp of a training image in,
the HOG of the other (original or warp) out (see :mod:`fdnet.methods.calc.model`).

Unsupervised: it uses every image of the configured conditions and frames, never which images
show the same place. What a resume needs beyond weights and the optimiser: the numpy generator
that draws images, warps and swaps. In a distributed run (torchrun) rank r's generator is seeded
with ``runtime.seed + r``, so every rank draws other images, and the gradients are averaged over
the ranks before each step.
"""

from __future__ import annotations

import numpy as np
import torch

from fdnet.backbones import unit_from_bytes
from fdnet.errors import ConfigError, DataError
from fdnet.methods.calc import model as calc
from fdnet.methods.calc.config import CALCRunConfig
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


def validate(config: CALCRunConfig) -> None:
    train = config.train
    if train.batch_size < 1 or train.steps < 0:
        raise ConfigError("train.batch_size must be >= 1 and train.steps >= 0")
    if not 0.0 <= train.swap_probability <= 1.0:
        raise ConfigError(f"train.swap_probability must be in [0, 1], got {train.swap_probability}")
    check_finite("optim.lr", config.optim.lr, positive=True)
    for name in ("momentum", "weight_decay"):
        check_finite(f"optim.{name}", getattr(config.optim, name))
    for name in ("checkpoint_every", "log_every"):
        if getattr(config.runtime, name) < 1:
            raise ConfigError(f"runtime.{name} must be >= 1")
    v = config.validation
    check_validation_pair(v)


class CALCTraining(TrainingMethod):
    name = "calc"
    log_columns = ("loss", "active_units")
    rank_state_keys = ("numpy_rng",)

    def __init__(self, config: CALCRunConfig, data: TrainingImages) -> None:
        validate(config)
        self.config = config
        model_cfg, train, rt = config.model, config.train, config.runtime
        self.input_size = tuple(int(v) for v in model_cfg.input_size)
        self.device = training_device(rt)
        self.rng = np.random.default_rng(self.distributed.rank_seed(rt.seed))  # per rank: other images
        torch.manual_seed(rt.seed)  # before building: the initial weights come from it
        self.network = calc.build_network(model_cfg).to(self.device)
        self.optimizer = make_optimizer(self.network.parameters(), config.optim)
        # grey uint8 (N, H, W) of every condition, and the HOG of each original (computed once)
        rgb = torch.cat(data.images).permute(0, 2, 3, 1).numpy()
        self.images = calc.to_grey_u8(rgb.astype(np.float32) / 255.0)
        if len(self.images) < train.batch_size:
            raise DataError(
                f"{config.data.root}: {len(self.images)} training images, fewer than one batch "
                f"({train.batch_size}); add images or lower train.batch_size"
            )
        self.hog = calc.hog_descriptor(model_cfg.hog)
        self.targets = calc.compute_hog(self.images, model_cfg.hog, self.hog)
        self.use_bf16 = training_precision(rt, self.device, native_only=True)
        # channels_last: oneDNN's convolutions run about twice as fast in it on CPU (measured)
        self.network.to(memory_format=torch.channels_last).train()

    def modules(self):
        return {"calc": self.network}

    def optimizers(self):
        return {"calc": self.optimizer}

    def loop_settings(self) -> LoopSettings:
        rt = self.config.runtime
        return LoopSettings(self.config.train.steps, rt.checkpoint_every, rt.log_every, self.config.validation.every)

    def start(self) -> None:
        if self.config.train.init_output_bias:
            # Start the decoder at the mean HOG (sigmoid^-1 of it) instead of 0.5 everywhere: the large
            # first-step error otherwise drives most bottleneck ReLUs dead before anything is learnt.
            mean = np.clip(self.targets.mean(axis=0), 1e-3, 1 - 1e-3)
            with torch.no_grad():
                bias = torch.from_numpy(np.log(mean / (1 - mean)).astype(np.float32))
                self.network.decoder[-2].bias.copy_(bias.to(self.device))

    def state(self) -> dict:
        return {"numpy_rng": numpy_rng_state(self.rng)}

    def load_state(self, state: dict) -> None:
        set_numpy_rng_state(self.rng, state["numpy_rng"])

    def train_step(self, step: int) -> dict[str, float]:
        train, model_cfg = self.config.train, self.config.model
        height, width = model_cfg.input_size
        self.network.train()
        batch = self.rng.integers(0, len(self.images), size=train.batch_size)
        inputs = np.empty((train.batch_size, height, width), np.uint8)
        target = np.empty((train.batch_size, self.targets.shape[1]), np.float32)
        for row, index in enumerate(batch):
            warped = calc.random_perspective_warp(self.images[index], self.rng)
            if self.rng.random() < train.swap_probability:
                # original in, HOG of the warp out
                inputs[row] = self.images[index]
                target[row] = calc.compute_hog(warped[None], model_cfg.hog, self.hog)[0]
            else:
                inputs[row] = warped
                target[row] = self.targets[index]
        x = unit_from_bytes(torch.from_numpy(inputs).to(self.device)[:, None])
        x = x.contiguous(memory_format=torch.channels_last)
        y = torch.from_numpy(target).to(self.device)
        with autocast(self.device, self.use_bf16):
            code = self.network.encode(x)
            prediction = self.network.decoder(code)
        loss = calc.euclidean_loss(prediction.float(), y)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        # False when the loss is not finite here or on another rank: every rank stops at this step
        if not self.distributed.average_gradients(self.optimizer, loss):
            raise FloatingPointError(f"CALC loss became {loss_text(loss)} at step {step}; lower optim.lr")
        self.optimizer.step()
        # share of bottleneck values above zero: 0 means every ReLU died and descriptors are all-zero
        active = float((code.detach() > 0).float().mean())
        if active == 0.0 and (step + 1) % self.config.runtime.log_every == 0:
            self.log(
                "warning: every CALC bottleneck unit is zero (dead ReLUs); descriptors carry no "
                "information. Lower optim.lr or restart with model.init=he"
            )
        return {"loss": float(loss.item()), "active_units": active}

    def validation_vectors(self, images: torch.Tensor) -> np.ndarray:
        grey = calc.to_grey_u8(images.permute(0, 2, 3, 1).numpy().astype(np.float32) / 255.0)
        x = unit_from_bytes(torch.from_numpy(grey).to(self.device)[:, None])
        was_training = self.network.training
        self.network.eval()
        with torch.inference_mode():
            out = self.network.encode(x).float()
        self.network.train(was_training)
        return torch.nn.functional.normalize(out, dim=1).cpu().numpy()


def train(
    config: CALCRunConfig,
    run_dir,
    resume: bool = False,
    override: bool = False,
    max_minutes: float | None = None,
    progress: bool = True,
    command: str = "fdnet train calc",
) -> dict:
    """Train CALC as ``config`` says into ``run_dir`` (what ``fdnet train calc`` calls)."""
    from fdnet.training.data import load_validation_images
    from fdnet.training.loop import run_training

    validate(config)

    def build():
        data = route_images(training_route(config.data), config.model.input_size, why="CALC")
        validation = load_validation_images(config.data.root, config.validation, config.model.input_size)
        method = CALCTraining(config, data)
        method.log(
            f"CALC: {sum(len(x) for x in data.images)} training images from {', '.join(data.names)} at "
            f"{config.model.input_size[0]}x{config.model.input_size[1]}, HOG targets "
            f"{method.targets.shape[1]}-d, descriptor {method.network.descriptor_dim}-d, on {method.device} "
            f"-> {run_dir}"
        )
        return method, validation

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
