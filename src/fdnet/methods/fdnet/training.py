"""FDNet's training step on the shared loop (paper eq. 10, Algorithm 1, section 4.1).

Stages, one after the other, counted in mini-batches ("steps"):

1. ``autoencoder``: E_c, E_a and the decoder on w_r * L_r (+ w_a * L_a);
2. ``critic``: D_a alone on L_d^adv (WGAN-GP), the encoders frozen;
3. ``joint``: per step, ``critic_updates_per_step`` updates of D_a and one update of E_c, E_a
   and the decoder on w_r L_r + w_a L_a + w_adv L_e^adv (paper: 2:1). With
   ``schedule.one_batch_per_step`` (the ``paper`` preset, Algorithm 1) the step samples one
   mini-batch X_b, updates the encoders/decoder on it, then D_a on its content vectors (new
   labelled pairs each time). Otherwise the D_a updates come first, sharing one batch's content
   vectors (or one batch each, ``schedule.critic_fresh_batches``), and the encoder/decoder update
   draws a batch of its own.

Ablation switches (``loss.adversarial``, ``loss.appearance_triplet``, ``loss.reconstruction``;
:class:`~fdnet.methods.fdnet.config.LossConfig`) remove a part from every stage: its loss is never
computed (nor the forward passes only it needs), its column is left out of ``log.csv``, and
without the critic D_a is never stepped and the critic stage is skipped
(:attr:`FDNetRunConfig.stage_steps`). A resumed run keeps the switches it started with.

What the checkpoint needs beyond weights and Adam states (the loop saves torch's global RNG,
used by dropout): the sampler's generator and the conditions trained on.

Distributed (torchrun, :mod:`fdnet.training.distributed`): rank r's sampler generator is seeded
with ``runtime.seed + 1 + r`` (rank 0: ``seed + 1``, as a single process), so every rank draws its
own domain-balanced batches, pairs and gradient-penalty interpolates; both optimisers step on
gradients averaged over the ranks (not DistributedDataParallel: the critic's gradient penalty is a
double backward, which DDP does not support).

No per-batch augmentation is applied: random photometric changes within a condition would blur
the very appearance differences between conditions that the appearance encoder and the
discriminator are meant to separate. Instead ``data.synthetic_conditions`` adds whole conditions
made by one named change each (:mod:`fdnet.data.appearance`), labelled as conditions of their own.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from fdnet.backbones import unit_from_bytes
from fdnet.config import replace_dotted
from fdnet.data.appearance import SEPARATOR, with_synthetic_conditions
from fdnet.errors import ConfigError
from fdnet.methods.fdnet import losses
from fdnet.methods.fdnet.config import (
    FDNetRunConfig,
    synthetic_option_text,
    validate,
)
from fdnet.methods.fdnet.model import TRUNK_HEADS, FDNet
from fdnet.methods.fdnet.run_start import (
    ablation_text,
    check_same_ablation,
    chosen_when_started,
    removed_columns,
    start_candidates,
    start_label,
)
from fdnet.methods.fdnet.sampler import DomainBalancedSampler
from fdnet.training.data import TrainingImages, route_images, training_route
from fdnet.training.distributed import loss_text
from fdnet.training.loop import LoopSettings, TrainingMethod, autocast, training_device, training_precision

log = logging.getLogger(__name__)


def _autocast(config: FDNetRunConfig, device: torch.device):
    """The encoders'/decoder's precision: bf16 autocast with ``runtime.bf16`` (losses stay float32)."""
    return autocast(device, training_precision(config.runtime, device))


def load_training_images(config: FDNetRunConfig) -> TrainingImages:
    """The run's training images (``config.data``) at the model's input size, with the synthetic
    appearance conditions ``config.data.synthetic_conditions`` added."""
    data = route_images(
        training_route(config.data),
        config.model.input_size,
        min_per_condition=config.data.batch_per_domain,
        min_conditions=2,
        why=f"FDNet (data.batch_per_domain = {config.data.batch_per_domain})",
    )
    return with_synthetic_conditions(data, config.data.synthetic_conditions, config.runtime.seed)


class FDNetTraining(TrainingMethod):
    """Owns FDNet's model, both optimisers and the domain-balanced sampler of one run."""

    name = "fdnet"
    log_columns = ("reconstruction", "appearance", "encoder_adversarial", "structure", "critic", "wasserstein")
    rank_state_keys = ("sampler_generator",)  # each rank's own stream; the conditions are shared

    def __init__(
        self, config: FDNetRunConfig, data: TrainingImages, trunk_maps: dict[tuple, torch.Tensor] | None = None
    ) -> None:
        """``trunk_maps``: the encoders' inputs by (block, condition[, synthetic setting]), shared by
        the candidates a run chooses from (:func:`choose_start`), filled as they are computed."""
        validate(config)
        self.config = config
        self.data = data
        self.input_size = tuple(int(v) for v in config.model.input_size)
        rt = config.runtime
        self.device = training_device(rt)  # and runtime.threads
        torch.manual_seed(rt.seed)
        self.model = FDNet(config.model).to(self.device)
        if rt.channels_last:
            self.model = self.model.to(memory_format=torch.channels_last)
        betas = (config.optim.beta1, config.optim.beta2)
        autoencoder_params = [
            p for name, m in self.model.named_parts().items() if name != "discriminator" for p in m.parameters()
        ]
        # fused=True: one kernel per tensor instead of ~10 passes; 3-4x faster on a loaded 2-core CPU,
        # where the Adam update of the 7M auto-encoder weights otherwise costs as much as the convs.
        self.opt_autoencoder = torch.optim.Adam(autoencoder_params, lr=config.optim.lr, betas=betas, fused=True)
        self.opt_critic = torch.optim.Adam(
            self.model.discriminator.parameters(), lr=config.optim.critic_lr, betas=betas, fused=True
        )
        # per rank (seed + 1 + rank): each rank of a distributed run draws other batches
        self.generator = torch.Generator().manual_seed(self.distributed.rank_seed(rt.seed + 1))
        self.sampler = DomainBalancedSampler(
            [len(x) for x in data.images], config.data.batch_per_domain, data.names, self.generator
        )
        self.domains = self.sampler.domain_labels().to(self.device)
        self.images = [x.to(self.device) for x in data.images]
        # With a frozen trunk, what the encoders read never changes (no augmentation), so it is
        # computed once: the trunk costs ~10 ms/image on a CPU core, more than the FDNet step.
        self.cached_inputs = (
            None
            if self.model.trunk is None
            else [self._trunk_map(x, name, trunk_maps) for x, name in zip(self.images, data.names)]
        )
        #: validation scores of each candidate start, by block (and synthetic setting; choose_start)
        self.block_selection: dict[str, dict[str, float]] = {}
        #: what the projection head's closed-form start found (content_fit.ProjectionFit.report)
        self.projection_fit: dict = {}
        #: log.csv's loss columns: those of the parts the ablation switches leave
        self.log_columns = tuple(c for c in type(self).log_columns if c not in removed_columns(config))

    # ------------------------------------------------------------------ loop interface
    def modules(self) -> dict[str, torch.nn.Module]:
        return self.model.named_parts()

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"autoencoder": self.opt_autoencoder, "critic": self.opt_critic}

    def loop_settings(self) -> LoopSettings:
        rt = self.config.runtime
        return LoopSettings(self.config.total_steps, rt.checkpoint_every, rt.log_every, self.config.validation.every)

    def stage(self, step: int) -> str:
        return self.config.stage_at(step)

    def start(self) -> None:
        from fdnet.methods.fdnet.model import TrunkProjectionContent, TrunkResidualContent

        head = self.model.content_encoder
        if not isinstance(head, (TrunkProjectionContent, TrunkResidualContent)):
            return
        inputs = self.cached_inputs or [self._preprocess(x) for x in self.images]
        if isinstance(head, TrunkProjectionContent):
            from fdnet.methods.fdnet.content_fit import fit_projection

            m = self.config.model
            fit = fit_projection(
                [x.flatten(1).cpu().numpy() for x in inputs],
                m.vector_length,
                init=m.projection_init,
                pca_dims=m.projection_pca_dims,
                pca_power=m.projection_pca_power,
                pair_sequence_length=m.pair_sequence_length,
                pair_shrinkage=m.pair_shrinkage,
                names=list(self.data.names),
            )
            head.set_start(fit.mean, fit.projection)
            self.projection_fit = fit.report
            self.log(
                f"content head starts in closed form ({m.projection_init}): "
                + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in fit.report.items())
            )
        else:
            # Centre on the mean map of every training image, all conditions pooled: the centred
            # trunk descriptor is where the residual head starts.
            head.set_mean(torch.cat(inputs))
            if self.config.model.residual_init == "condition_means":
                removed = head.remove_condition_means(inputs)
                self.log(
                    f"content head starts with {removed} direction(s) between the conditions' " "mean maps removed"
                )

    def state(self) -> dict:
        return {
            "sampler_generator": self.generator.get_state(),
            "conditions": list(self.data.names),
            "block_selection": self.block_selection,
            "projection_fit": self.projection_fit,
        }

    def load_state(self, state: dict) -> None:
        if list(state.get("conditions", self.data.names)) != list(self.data.names):
            raise ConfigError(f"the run was trained on conditions {state['conditions']}, now given {self.data.names}")
        self.generator.set_state(state["sampler_generator"])
        self.block_selection = dict(state.get("block_selection", {}))
        self.projection_fit = dict(state.get("projection_fit", {}))

    def validation_vectors(self, images: torch.Tensor) -> np.ndarray:
        rt = self.config.runtime
        vectors = content_vectors(self.model, images, self.device, rt.bf16, rt.channels_last)
        return torch.nn.functional.normalize(vectors, dim=1).numpy()

    # ------------------------------------------------------------------ one step
    def _trunk_map(self, images: torch.Tensor, condition: str, shared: dict | None) -> torch.Tensor:
        """The encoders' input for one condition's images, from ``shared`` when another candidate
        of the same block computed it. A real condition's images are the same in every candidate;
        a synthetic one's depend on the whole synthetic setting (one generator draws them all), so
        its key carries that setting."""
        desc = f"trunk maps [block {self.config.model.backbone_block}, {condition}]"
        if shared is None:
            return self._preprocess(images, desc=desc)
        key = (int(self.config.model.backbone_block), condition)
        if SEPARATOR in condition:
            key += (tuple(self.config.data.synthetic_conditions),)
        if key not in shared:
            shared[key] = self._preprocess(images, desc=desc)
        return shared[key]

    def _preprocess(self, images: torch.Tensor, chunk: int = 64, desc: str | None = None) -> torch.Tensor:
        """uint8 (N, 3, H, W) -> what the encoders read (``FDNet.preprocess``), in chunks; with
        ``desc``, a progress bar with the time left (a condition's trunk maps take minutes on a
        large route; a training batch has none)."""
        from fdnet.progress import progress_bar

        out = []
        bar = progress_bar(total=len(images), desc=desc, unit="img", leave=False) if desc else None
        for start in range(0, len(images), chunk):
            x = unit_from_bytes(images[start : start + chunk])
            if self.config.runtime.channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            with torch.no_grad(), _autocast(self.config, self.device):
                out.append(self.model.preprocess(x).float())
            if bar is not None:
                bar.update(len(x))
        if bar is not None:
            bar.close()
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

    def _critic_features(self, x: torch.Tensor | None = None) -> torch.Tensor:
        """Content vectors of batch ``x`` (default: a fresh one) for D_a updates (no gradient to
        the encoder)."""
        model, cfg = self.model, self.config
        x = self._batch() if x is None else x
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
            self.model.discriminator.forward_pairs,
            losses.pair_vectors(content, same),
            losses.pair_vectors(content, different),
            cfg.loss.gradient_penalty_weight,
            self.generator,
        )
        self.opt_critic.zero_grad(set_to_none=True)
        loss.backward()
        self.distributed.average_gradients(self.opt_critic)  # incl. the penalty's double backward
        self.opt_critic.step()
        return {"critic": float(loss.detach()), "wasserstein": float(distance)}

    def _autoencoder_update(
        self, step: int, adversarial: bool, appearance: bool, target: torch.Tensor | None = None
    ) -> dict[str, float]:
        """One update of E_c, E_a and the decoder on the terms asked for (``adversarial``: L_e^adv,
        ``appearance``: L_a) that the ablation switches leave, plus L_r unless it is switched off.
        Only the passes those terms need are computed; with no term left nothing is updated."""
        model, cfg = self.model, self.config
        adversarial = adversarial and cfg.loss.adversarial
        appearance = appearance and cfg.loss.appearance_triplet
        rebuild = cfg.loss.reconstruction
        if not (adversarial or appearance or rebuild):
            return {}
        target = self._batch() if target is None else target
        # the trunk heads keep the trunk's information by construction; only L_e^adv moves them
        trunk_head = cfg.model.content_head in TRUNK_HEADS
        total = torch.zeros((), device=self.device)
        out: dict[str, float] = {}
        with _autocast(cfg, self.device):
            content = model.content_encoder(target) if (rebuild or adversarial) else None
            appearance_vec = model.appearance_encoder(target) if (rebuild or appearance) else None
            reconstruction = (
                model.decoder(content.detach() if trunk_head else content, appearance_vec) if rebuild else None
            )
        if rebuild:
            rec = losses.reconstruction_loss(target, reconstruction, cfg.loss.reconstruction_reduction)
            total = total + cfg.loss.reconstruction_weight * rec
            out["reconstruction"] = float(rec.detach())
        if appearance:
            app_vectors = appearance_vec.float()
            if cfg.loss.triplet_vectors == "l2":
                app_vectors = torch.nn.functional.normalize(app_vectors, dim=1)
            app = losses.batch_hard_triplet_loss(app_vectors, self.domains, cfg.loss.triplet_margin)
            total = total + cfg.loss.appearance_weight * app
            out["appearance"] = float(app.detach())
        if adversarial:
            features = model.critic_features(content.float())
            same, different = losses.sample_pairs(self.domains, self.generator)
            critic = model.discriminator
            critic.requires_grad_(False)  # only E_c learns from L_e^adv here
            adv = losses.encoder_adversarial_loss(
                critic.forward_pairs, losses.pair_vectors(features, same), losses.pair_vectors(features, different)
            )
            critic.requires_grad_(True)
            total = total + cfg.loss.adversarial_weight * adv
            out["encoder_adversarial"] = float(adv.detach())
            if cfg.loss.structure_weight > 0:
                # the reference is what the head reads: the residual head's own centring, or for a
                # learnt encoder its flattened input centred on the batch
                if trunk_head:
                    reference = model.content_encoder.centred(target)
                else:
                    reference = target.flatten(1).float()
                    reference = reference - reference.mean(0)
                structure = losses.structure_loss(content.float(), reference, self.domains)
                total = total + cfg.loss.structure_weight * structure
                out["structure"] = float(structure.detach())
        self.opt_autoencoder.zero_grad(set_to_none=True)
        total.backward()
        # False when the loss is not finite here or on another rank: every rank stops at this step
        if not self.distributed.average_gradients(self.opt_autoencoder, total):
            raise FloatingPointError(
                f"loss became {loss_text(total)} at step {step}; lower optim.lr or the loss " "weights"
            )
        self.opt_autoencoder.step()
        return out

    def train_step(self, step: int) -> dict[str, float]:
        stage = self.config.stage_at(step)
        self._set_lr(stage)
        self.model.train()
        out: dict[str, float] = {}
        # without the critic (loss.adversarial=false) there is no critic stage and no D_a update
        critic_updates = self.config.schedule.critic_updates_per_step if self.config.loss.adversarial else 0
        if stage == "autoencoder":
            out.update(
                self._autoencoder_update(step, adversarial=False, appearance=self.config.loss.appearance_in_pretraining)
            )
        elif stage == "critic":
            out.update(self._critic_update(self._critic_features()))
        elif self.config.schedule.one_batch_per_step:
            batch = self._batch()
            out.update(self._autoencoder_update(step, adversarial=True, appearance=True, target=batch))
            if critic_updates:
                content = self._critic_features(batch)
                for _ in range(critic_updates):
                    out.update(self._critic_update(content))
        else:
            # The D_a updates of one step share one batch's content vectors (each draws new
            # pairs), or take a batch each with schedule.critic_fresh_batches: one encoder
            # forward instead of several is ~20% of a step on a 2-core CPU.
            content = None
            for _ in range(critic_updates):
                if content is None or self.config.schedule.critic_fresh_batches:
                    content = self._critic_features()
                out.update(self._critic_update(content))
            out.update(self._autoencoder_update(step, adversarial=True, appearance=True))
        return out


def content_vectors(
    model: FDNet,
    images: torch.Tensor,
    device: torch.device,
    bf16: bool = False,
    channels_last: bool = False,
    batch: int = 256,
    appearance: bool = False,
) -> torch.Tensor:
    """uint8 (N, 3, H, W) -> float32 (N, L) content (or appearance) vectors, eval mode."""
    was_training = model.training
    model.eval()
    out = []
    with torch.inference_mode():
        for start in range(0, len(images), batch):
            x = unit_from_bytes(images[start : start + batch].to(device))
            if channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            with autocast(device, bf16):
                v = model.appearance(x) if appearance else model.content(x)
            out.append(v.float().cpu())
    model.train(was_training)
    return torch.cat(out) if out else torch.zeros((0, model.content_length))


def choose_start(
    config: FDNetRunConfig, real: TrainingImages, validation, deadline: float | None = None, progress: bool = True
) -> FDNetTraining:
    """The FDNet training whose closed-form content start scores best on ``validation`` among
    :func:`start_candidates`: R@1, ties to the higher AUC, then to the earlier candidate, as
    ``best/`` is chosen. ``real`` are the training images without synthetic conditions. Each
    candidate is built as a run of its own and started (:meth:`FDNetTraining.start`: no gradient
    step); the trunk maps of a condition are computed once per block and shared between the
    candidates. The scores are kept in ``block_selection``. The chosen one comes back in the state
    a run of those settings alone would have (torch's RNG as after building it), so choosing does
    not change what training then does.

    ``deadline`` (a :func:`time.monotonic` time: ``--max-minutes`` bounds the whole command) stops
    the choice after the first candidate that ends past it, keeping the best of those scored (a
    run on several processes scores every candidate: its ranks must choose alike)."""
    import time

    from fdnet.progress import progress_bar
    from fdnet.training import distributed
    from fdnet.training.loop import validation_metrics

    best, scores, maps = None, {}, {}
    candidates = start_candidates(config)
    if distributed.current().enabled:
        deadline = None
    # each candidate takes minutes on a large route: a bar with the time left (fdnet.progress)
    bar = progress_bar(total=len(candidates), desc="choosing the start", unit="start") if progress else None
    for number, (option, block) in enumerate(candidates):
        if deadline is not None and number and time.monotonic() >= deadline:
            log.warning(
                f"--max-minutes: the time ran out while choosing the start, after {number} of "
                f"{len(candidates)} candidates; training the best of those (give one start to skip the "
                'choice: docs/guide.md, "One start")'
            )
            break
        settings = {"model.backbone_block": int(block), "data.synthetic_conditions": list(option)}
        data = with_synthetic_conditions(real, option, config.runtime.seed)
        method = FDNetTraining(replace_dotted(config, settings), data, trunk_maps=maps)
        rng = torch.get_rng_state()
        method.log = lambda message: None  # start() says what it removed; once, when training starts
        method.start()
        metrics = validation_metrics(method, validation)
        label = start_label(config, option, block)
        scores[label] = {k: float(v) for k, v in metrics.items()}
        log.info(
            f"trunk block {label}: validation R@1 {metrics['recall@1']:.3f}, " f"AUC {metrics['auc']:.3f} at the start"
        )
        key = (metrics["recall@1"], metrics["auc"])
        if best is None or key > best[0]:
            best = (key, method, rng)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    _, method, rng = best
    torch.set_rng_state(rng)
    method.block_selection = scores
    del method.log  # back to the class's
    chosen_block = method.config.model.backbone_block
    chosen = start_label(config, tuple(method.config.data.synthetic_conditions), chosen_block)
    note = (
        ""
        if chosen_block == config.model.backbone_block
        else (
            f"; model.backbone_block = {config.model.backbone_block} is the block for runs without a validation pair, "
            "set model.backbone_block_candidates=[] to train it regardless"
        )
    )
    log.info(
        f"training on trunk block {chosen} " f"(of {', '.join(start_label(config, o, b) for o, b in candidates)}){note}"
    )
    return method


def train(
    config: FDNetRunConfig,
    run_dir,
    resume: bool = False,
    override: bool = False,
    max_minutes: float | None = None,
    progress: bool = True,
    command: str = "fdnet train",
) -> dict:
    """Train FDNet as ``config`` says into ``run_dir`` (what ``fdnet train`` calls)."""
    import time

    from fdnet.training.data import load_validation_images
    from fdnet.training.loop import run_training

    validate(config)  # settings errors before any image is read
    # --max-minutes bounds the whole command: choosing the start spends from it too
    deadline = None if max_minutes is None else time.monotonic() + 60.0 * float(max_minutes)

    def build():
        if resume:
            check_same_ablation(config, run_dir)
        if config.ablated():
            autoencoder, critic, joint = config.stage_steps
            log.info(f"ablation: {ablation_text(config)}; stages of {autoencoder} + {critic} + {joint} steps")
        candidates = start_candidates(config)
        run_config = chosen_when_started(config, run_dir) if resume and len(candidates) > 1 else config
        real = load_training_images(replace_dotted(config, {"data.synthetic_conditions": []}))
        validation = load_validation_images(config.data.root, config.validation, config.model.input_size)
        log.info(
            f"preset {config.preset}, conditions {', '.join(real.names)} "
            f"({', '.join(str(len(x)) for x in real.images)} images), input {tuple(config.model.input_size)}, "
            f"{config.total_steps} steps -> {run_dir}"
        )
        if len(candidates) > 1 and not resume:
            if validation is not None:
                return choose_start(config, real, validation, deadline, progress), validation
            log.info(
                f"no validation pair to choose a start from "
                f"({', '.join(start_label(config, o, b) for o, b in candidates)}); training on "
                f"model.backbone_block = {config.model.backbone_block}, data.synthetic_conditions = "
                f"{synthetic_option_text(config.data.synthetic_conditions)}"
            )
        data = with_synthetic_conditions(real, run_config.data.synthetic_conditions, run_config.runtime.seed)
        if len(data.names) > len(real.names):
            log.info(
                f"training also on the synthetic conditions {', '.join(data.names[len(real.names):])}, made "
                "from the real ones (the preset's data.synthetic_conditions, or chosen on the validation pair "
                "among data.synthetic_conditions_candidates; --set data.synthetic_conditions_candidates=[] "
                "--set data.synthetic_conditions=[] trains on the real conditions only; README)"
            )
        return FDNetTraining(run_config, data), validation

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
