"""Staged adversarial training of FDNet (paper eq. 10, Algorithm 1, section 4.1).

Stages, one after the other, counted in mini-batches ("steps"):

1. ``autoencoder``: E_c, E_a and the decoder on w_r * L_r (+ w_a * L_a);
2. ``critic``: D_a alone on L_d^adv (WGAN-GP), the encoders frozen;
3. ``joint``: per step, ``critic_updates_per_step`` updates of D_a (each on a fresh batch), then
   one update of E_c, E_a and the decoder on w_r L_r + w_a L_a + w_adv L_e^adv (paper: 2:1).

Everything the run needs to continue exactly is in the checkpoint: weights, both Adam states,
the step counter, the sampler's generator and torch's global RNG (dropout). ``--resume``
therefore reproduces the uninterrupted run (same thread count, same machine). Ctrl-C and
``max_minutes`` finish the current step, write a checkpoint and stop.

No data augmentation is applied: none was needed for the results in docs/results.md, and
photometric augmentation would blur the very appearance differences between conditions that
the appearance encoder and the discriminator are meant to separate.
"""

from __future__ import annotations

import contextlib
import signal
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fdnet.data.dataset import RouteDataset, parse_frame_range
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.images import load_images
from fdnet.errors import ConfigError, DataError
from fdnet.io import atomic_write_text
from fdnet.models.fdnet import FDNet
from fdnet.training import losses
from fdnet.training.checkpoint import (
    STATE_FILE, WEIGHTS_FILE, check_config, load_config, load_training_state, load_weights, save_run,
)
from fdnet.training.config import TrainConfig, model_keys, validate
from fdnet.training.logging import TrainingLog
from fdnet.training.sampler import DomainBalancedSampler

BEST_DIR = "best"


# ----------------------------------------------------------------------------- data
@dataclass
class TrainingImages:
    """Training images held in memory as uint8 (N, 3, H, W) per condition: decoding image files
    every step would cost more than the network on a 2-core CPU."""

    names: list[str]
    images: list[torch.Tensor]


def to_uint8_tensor(images: np.ndarray) -> torch.Tensor:
    """(N, H, W, 3) float [0, 1] -> (N, 3, H, W) uint8."""
    return torch.from_numpy(np.clip(np.rint(images * 255.0), 0, 255).astype(np.uint8)).permute(0, 3, 1, 2).contiguous()


def load_training_images(root: str | Path, conditions, frames: str, size, batch_per_domain: int) -> TrainingImages:
    """Read ``root/<condition>/`` (the frame slice of each) at ``size``; checks counts first."""
    dataset = RouteDataset.from_folder(root, list(conditions) or None)
    start, end = parse_frame_range(frames)
    return route_training_images(dataset.frames(start, end), size, batch_per_domain, frames)


def route_training_images(dataset: RouteDataset, size, batch_per_domain: int,
                          frames: str = "") -> TrainingImages:
    """The images of every condition of ``dataset`` (e.g. a dataset adapter's training split)
    at ``size``; checks counts first."""
    root = dataset.root
    if len(dataset.conditions) < 2:
        raise DataError(
            f"{root}: FDNet needs at least two conditions (sub-folders) to train on; "
            f"found {', '.join(dataset.conditions) or 'none'}"
        )
    for name in dataset.conditions:
        if len(dataset[name]) < batch_per_domain:
            raise DataError(
                f"{Path(root) / name}: {len(dataset[name])} images in frames {frames or 'all'}, fewer than "
                f"data.batch_per_domain = {batch_per_domain}"
            )
    images = [to_uint8_tensor(load_images(dataset[name].paths, size)) for name in dataset.conditions]
    return TrainingImages(dataset.conditions, images)


@dataclass
class ValidationImages:
    reference: torch.Tensor
    query: torch.Tensor
    ground_truth: GroundTruth
    description: str


def load_validation_images(root: str | Path, config: TrainConfig) -> ValidationImages | None:
    v = config.validation
    if not v.reference:
        return None
    dataset = RouteDataset.from_folder(root, [v.reference, v.query])
    start, end = parse_frame_range(v.frames)
    dataset = dataset.frames(start, end)
    ref, query = dataset[v.reference], dataset[v.query]
    gt = GroundTruth.from_frames(query.frame_ids, ref.frame_ids, v.tolerance)
    if not gt.has_match.any():
        raise DataError(f"validation {v.query}->{v.reference} frames {v.frames or 'all'}: no query has a match")
    size = config.model.input_size
    return ValidationImages(
        to_uint8_tensor(load_images(ref.paths, size)), to_uint8_tensor(load_images(query.paths, size)), gt,
        f"{v.query}->{v.reference} frames {v.frames or 'all'} tolerance {v.tolerance}",
    )


# ----------------------------------------------------------------------------- helpers
def _autocast(config: TrainConfig, device: torch.device):
    if not config.runtime.bf16:
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16)


def content_vectors(model: FDNet, images: torch.Tensor, device: torch.device, bf16: bool = False,
                    channels_last: bool = False, batch: int = 256, appearance: bool = False) -> torch.Tensor:
    """uint8 (N, 3, H, W) -> float32 (N, L) content (or appearance) vectors, eval mode."""
    was_training = model.training
    model.eval()
    out = []
    with torch.inference_mode():
        for start in range(0, len(images), batch):
            x = images[start:start + batch].to(device).float().div_(255.0)
            if channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            with torch.autocast(device.type, dtype=torch.bfloat16) if bf16 else contextlib.nullcontext():
                v = model.appearance(x) if appearance else model.content(x)
            out.append(v.float().cpu())
    model.train(was_training)
    return torch.cat(out) if out else torch.zeros((0, model.config.vector_length))


def validation_metrics(model: FDNet, data: ValidationImages, device: torch.device, bf16: bool,
                       channels_last: bool) -> dict[str, float]:
    """R@1, R@5 and R@100P (recall over queries with a match) of cosine matching."""
    from fdnet.evaluation.metrics import evaluate_similarity

    ref = torch.nn.functional.normalize(content_vectors(model, data.reference, device, bf16, channels_last), dim=1)
    qry = torch.nn.functional.normalize(content_vectors(model, data.query, device, bf16, channels_last), dim=1)
    metrics = evaluate_similarity((qry @ ref.T).numpy(), data.ground_truth, ns=(1, 5))
    return {"recall@1": metrics.recall_at_n[1], "recall@5": metrics.recall_at_n[5],
            "recall@100p": metrics.recall_at_100_precision, "auc": metrics.auc_pr}


class _StopRequest:
    """SIGINT handler that lets the current step finish (a half-applied optimiser step would
    leave weights and step counter out of sync); the loop then checkpoints and stops."""

    def __init__(self) -> None:
        self.requested = False
        self._previous = None

    def __enter__(self):
        try:
            self._previous = signal.signal(signal.SIGINT, self._handle)
        except ValueError:  # not in the main thread: Ctrl-C handling stays Python's default
            self._previous = None
        return self

    def _handle(self, signum, frame) -> None:
        if self.requested:  # second Ctrl-C: give up waiting
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


# ----------------------------------------------------------------------------- trainer
class Trainer:
    """Owns the model, optimisers, sampler and run directory of one training run."""

    def __init__(self, config: TrainConfig, data: TrainingImages, run_dir: str | Path,
                 validation: ValidationImages | None = None, resume: bool = False,
                 tensorboard: bool = True) -> None:
        validate(config)
        self.config = config
        self.run_dir = Path(run_dir)
        self.data = data
        self.validation = validation
        rt = config.runtime
        if rt.threads > 0:
            torch.set_num_threads(rt.threads)
        self.device = torch.device(rt.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ConfigError("runtime.device=cuda but no CUDA device is available here")

        torch.manual_seed(rt.seed)
        self.model = FDNet(config.model).to(self.device)
        if rt.channels_last:
            self.model = self.model.to(memory_format=torch.channels_last)
        betas = (config.optim.beta1, config.optim.beta2)
        autoencoder_params = [p for name, m in self.model.named_parts().items() if name != "discriminator"
                              for p in m.parameters()]
        # fused=True: one kernel per tensor instead of ~10 passes; 3-4x faster on a loaded 2-core CPU,
        # where the Adam update of the 7M auto-encoder weights otherwise costs as much as the convs.
        self.opt_autoencoder = torch.optim.Adam(autoencoder_params, lr=config.optim.lr, betas=betas, fused=True)
        self.opt_critic = torch.optim.Adam(self.model.discriminator.parameters(), lr=config.optim.critic_lr,
                                           betas=betas, fused=True)
        self.generator = torch.Generator().manual_seed(rt.seed + 1)
        self.sampler = DomainBalancedSampler([len(x) for x in data.images], config.data.batch_per_domain,
                                             data.names, self.generator)
        self.domains = self.sampler.domain_labels().to(self.device)
        self.images = [x.to(self.device) for x in data.images]
        # With a frozen trunk, what the encoders read never changes (no augmentation), so it is
        # computed once: the trunk costs ~10 ms/image on a CPU core, more than the FDNet step.
        self.cached_inputs = None if self.model.trunk is None else [self._preprocess(x) for x in self.images]
        self.step = 0
        self.elapsed = 0.0
        self.best = {"step": -1, "recall@1": -1.0, "auc": -1.0}
        self.last_validation: dict[str, float] = {}
        self.log = TrainingLog(self.run_dir, tensorboard=tensorboard)
        if resume:
            self._resume()
        elif (self.run_dir / WEIGHTS_FILE).exists():
            raise ConfigError(f"{self.run_dir}: already holds a run; use --resume to continue it or choose another --out")

    # ------------------------------------------------------------------ checkpoints
    def _state(self) -> dict:
        return {
            "step": self.step,
            "elapsed_seconds": self.elapsed,
            "stage": self.config.stage_at(max(self.step - 1, 0)),
            "sampler_generator": self.generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "best_step": self.best["step"],
            "best_recall@1": float(self.best["recall@1"]),
            "best_auc": float(self.best["auc"]),
            "conditions": list(self.data.names),
        }

    def save(self) -> Path:
        return save_run(self.run_dir, self.model.named_parts(), self.config,
                        optimizers={"autoencoder": self.opt_autoencoder, "critic": self.opt_critic},
                        state=self._state())

    def _resume(self) -> None:
        if not (self.run_dir / STATE_FILE).exists():
            raise ConfigError(f"{self.run_dir}: nothing to resume (no {STATE_FILE}); start a new run without --resume")
        saved = load_config(self.run_dir, TrainConfig)
        check_config(self.run_dir, saved, self.config, keys=model_keys())
        load_weights(self.run_dir, self.model.named_parts(), device=self.device)
        state = load_training_state(self.run_dir, {"autoencoder": self.opt_autoencoder, "critic": self.opt_critic})
        if list(state.get("conditions", self.data.names)) != list(self.data.names):
            raise ConfigError(f"{self.run_dir}: was trained on conditions {state['conditions']}, "
                              f"now given {self.data.names}")
        self.step = int(state["step"])
        self.elapsed = float(state["elapsed_seconds"])
        self.generator.set_state(state["sampler_generator"])
        torch.set_rng_state(state["torch_rng"])
        self.best = {"step": int(state["best_step"]), "recall@1": float(state["best_recall@1"]),
                     "auc": float(state.get("best_auc", -1.0))}
        self.log.truncate_after(self.step)

    # ------------------------------------------------------------------ one step
    def _preprocess(self, images: torch.Tensor, chunk: int = 64) -> torch.Tensor:
        """uint8 (N, 3, H, W) -> what the encoders read (``FDNet.preprocess``), in chunks."""
        out = []
        for start in range(0, len(images), chunk):
            x = images[start:start + chunk].float().div_(255.0)
            if self.config.runtime.channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            with torch.no_grad(), _autocast(self.config, self.device):
                out.append(self.model.preprocess(x).float())
        return torch.cat(out)

    def _batch(self) -> torch.Tensor:
        """One domain-balanced mini-batch of encoder inputs (preprocessed images or trunk maps)."""
        idx = self.sampler.sample()
        if self.cached_inputs is not None:
            return torch.cat([inputs[i.to(inputs.device)] for inputs, i in zip(self.cached_inputs, idx)])
        return self._preprocess(torch.cat([imgs[i.to(imgs.device)] for imgs, i in zip(self.images, idx)]))

    def _set_lr(self, stage: str) -> None:
        scale = self.config.optim.joint_lr_scale if stage == "joint" else 1.0
        for group in self.opt_autoencoder.param_groups:
            group["lr"] = self.config.optim.lr * scale

    def _critic_features(self) -> torch.Tensor:
        """Content vectors of a fresh batch for D_a updates (no gradient to the encoder)."""
        model, cfg = self.model, self.config
        x = self._batch()
        encoder = model.content_encoder
        mode = encoder.training
        encoder.train(cfg.runtime.critic_encoder_mode == "train")
        with torch.no_grad(), _autocast(cfg, self.device):
            content = model.critic_features(model.content_encoder(x).float())
        encoder.train(mode)
        return content

    def _critic_update(self, content: torch.Tensor) -> dict[str, float]:
        """One D_a update on (detached) content vectors, with freshly drawn labelled pairs."""
        cfg = self.config
        same, different = losses.sample_pairs(self.domains, self.generator)
        loss, distance = losses.critic_loss(
            self.model.discriminator.forward_pairs, losses.pair_vectors(content, same),
            losses.pair_vectors(content, different), cfg.loss.gradient_penalty_weight, self.generator,
        )
        self.opt_critic.zero_grad(set_to_none=True)
        loss.backward()
        self.opt_critic.step()
        return {"critic": float(loss.detach()), "wasserstein": float(distance)}

    def _autoencoder_update(self, adversarial: bool, appearance: bool) -> dict[str, float]:
        model, cfg = self.model, self.config
        target = self._batch()
        with _autocast(cfg, self.device):
            content = model.content_encoder(target)
            appearance_vec = model.appearance_encoder(target)
            reconstruction = model.decoder(content, appearance_vec)
        rec = losses.reconstruction_loss(target, reconstruction)
        total = cfg.loss.reconstruction_weight * rec
        out = {"reconstruction": float(rec.detach())}
        if appearance:
            app = losses.batch_hard_triplet_loss(appearance_vec.float(), self.domains, cfg.loss.triplet_margin)
            total = total + cfg.loss.appearance_weight * app
            out["appearance"] = float(app.detach())
        if adversarial:
            features = model.critic_features(content.float())
            same, different = losses.sample_pairs(self.domains, self.generator)
            critic = model.discriminator
            critic.requires_grad_(False)  # only E_c learns from L_e^adv here
            adv = losses.encoder_adversarial_loss(critic.forward_pairs, losses.pair_vectors(features, same),
                                                  losses.pair_vectors(features, different))
            critic.requires_grad_(True)
            total = total + cfg.loss.adversarial_weight * adv
            out["encoder_adversarial"] = float(adv.detach())
        if not torch.isfinite(total):
            raise FloatingPointError(f"loss became {float(total)} at step {self.step}; lower optim.lr or the loss weights")
        self.opt_autoencoder.zero_grad(set_to_none=True)
        total.backward()
        self.opt_autoencoder.step()
        return out

    def train_step(self) -> dict[str, float]:
        stage = self.config.stage_at(self.step)
        self._set_lr(stage)
        self.model.train()
        out: dict[str, float] = {}
        if stage == "autoencoder":
            out.update(self._autoencoder_update(adversarial=False,
                                                appearance=self.config.loss.appearance_in_pretraining))
        elif stage == "critic":
            out.update(self._critic_update(self._critic_features()))
        else:
            # The D_a updates of one step share one batch's content vectors (each draws new
            # pairs), or take a batch each with schedule.critic_fresh_batches: one encoder
            # forward instead of several is ~20% of a step on a 2-core CPU.
            content = None
            for _ in range(self.config.schedule.critic_updates_per_step):
                if content is None or self.config.schedule.critic_fresh_batches:
                    content = self._critic_features()
                out.update(self._critic_update(content))
            out.update(self._autoencoder_update(adversarial=True, appearance=True))
        self.step += 1
        return out

    # ------------------------------------------------------------------ validation
    def validate_now(self) -> dict[str, float]:
        rt = self.config.runtime
        metrics = validation_metrics(self.model, self.validation, self.device, rt.bf16, rt.channels_last)
        self.last_validation = metrics
        # R@1 first; ties (frequent on small validation sets, where R@1 saturates) go to the
        # higher area under the PR curve, which keeps moving after R@1 has stopped.
        if (metrics["recall@1"], metrics["auc"]) > (self.best["recall@1"], self.best["auc"]):
            self.best = {"step": self.step, "recall@1": metrics["recall@1"], "auc": metrics["auc"]}
            best_dir = self.run_dir / BEST_DIR
            save_run(best_dir, self.model.named_parts(), self.config)
            lines = [f"step: {self.step}", f"validation: {self.validation.description!r}"]
            lines += [f"{k}: {v:.6f}" for k, v in metrics.items()]
            atomic_write_text(best_dir / "validation.yaml", "\n".join(lines) + "\n")
        return metrics

    # ------------------------------------------------------------------ loop
    def fit(self, max_minutes: float | None = None, progress: bool = True) -> dict:
        """Train until the schedule ends, ``max_minutes`` pass or Ctrl-C; always checkpoint.

        Returns a summary dict (``status`` is "finished", "time limit" or "interrupted").
        Re-raises KeyboardInterrupt after saving when interrupted.
        """
        cfg = self.config
        total = cfg.total_steps
        rt = cfg.runtime
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=total, initial=self.step, unit="step", dynamic_ncols=True)
        status = "finished"
        started = time.monotonic()
        base_elapsed = self.elapsed
        last_saved = self.step
        interrupted = False
        with _StopRequest() as stop:
            while self.step < total:
                losses_now = self.train_step()
                self.elapsed = base_elapsed + time.monotonic() - started
                stage = cfg.stage_at(self.step - 1)
                row = None
                if self.validation is not None and (self.step % cfg.validation.every == 0 or self.step == total):
                    metrics = self.validate_now()
                    row = {"val_recall@1": metrics["recall@1"], "val_recall@100p": metrics["recall@100p"]}
                if self.step % rt.log_every == 0 or row is not None or self.step == total:
                    self.log.write({"step": self.step, "stage": stage, "elapsed_s": round(self.elapsed, 2),
                                    **losses_now, **(row or {})})
                if self.step % rt.checkpoint_every == 0:
                    self.save()
                    last_saved = self.step
                if bar is not None:
                    bar.update(1)
                    shown = {k[:5]: f"{v:.3g}" for k, v in losses_now.items()}
                    if self.last_validation:
                        shown["valR@1"] = f"{self.last_validation['recall@1']:.3f}"
                    bar.set_description(stage)
                    bar.set_postfix(shown, refresh=False)
                if stop.requested:
                    status, interrupted = "interrupted", True
                    break
                if max_minutes is not None and time.monotonic() - started >= max_minutes * 60.0:
                    status = "time limit"
                    break
        if bar is not None:
            bar.close()
        if last_saved != self.step or not (self.run_dir / WEIGHTS_FILE).exists():
            self.save()
        self.log.close()
        summary = {"status": status, "step": self.step, "total_steps": total,
                   "elapsed_seconds": self.elapsed, "run_dir": str(self.run_dir),
                   "best_step": self.best["step"], "best_recall@1": self.best["recall@1"]}
        if interrupted:
            raise KeyboardInterrupt(summary)
        return summary
