"""Training configuration: one dataclass tree, five presets, YAML/CLI overrides.

``FDNetRunConfig`` is written to ``RUN_DIR/config.yaml`` so every run says how it was made. Presets:

* ``paper`` - the paper's settings (section 4.1): 224x224 input, batch 4 per domain, Adam
  lr 1e-4 beta1 0.5, 5000 auto-encoder + 8000 discriminator pretraining steps, then 60000 joint
  steps with 2 discriminator updates per encoder/decoder update. Meant for a GPU
  (``runtime.device=cuda``).
* ``paper-native`` - the paper's recipe run to its end on 2 CPU cores: ``paper`` at Nordland's
  native 32x64 with four blocks of the paper's widths 64..512, bf16 autocast and channels_last
  (the 73,000 steps took 2.0-2.65 h, median 2.3 h, on 2 idle cores; docs/runs.md has the measurements).
* ``cpu`` - sized for at most ~20 minutes on 2 CPU cores: FDNet on the map of a frozen ImageNet
  trunk (EfficientNet-Lite0, ``model.backbone``) at 128x256 with the projection content head
  (``model.content_head=trunk_projection``, L = 512) that starts in closed form from pairs mined
  across the training conditions; with a validation pair the trunk block (7 or 11) and a
  synthetic night copy (or none) are chosen on it. docs/results.md has its numbers against the
  trunk alone, the whitened trunk and every baseline.
* ``cpu-scratch`` - the paper's pixel encoders learnt from scratch at 32x64, for 2 CPU cores
  (Nordland R@1 0.31 in 3 minutes; below SAD on Gardens Point).
  docs/results.md logs every run behind these numbers. Under heavy load from other processes
  a run may need ``--max-minutes`` and ``--resume``.
* ``tiny`` - a few seconds, for tests.

Any field can be overridden: ``--set schedule.joint_steps=3000`` or ``--config my.yaml``
(a YAML file holding any subset of the tree, applied on top of the preset).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from fdnet.config import apply_yaml, to_dict
from fdnet.errors import ConfigError
from fdnet.methods.fdnet.model import FDNetConfig, validate_architecture
from fdnet.methods.settings import DataConfig, ValidationConfig, check_finite, check_validation_pair
from fdnet.methods.settings import RuntimeConfig as SharedRuntimeConfig


@dataclass
class FDNetDataConfig(DataConfig):
    #: B, images per condition in a mini-batch (paper: 4)
    batch_per_domain: int = 4
    #: synthetic appearance conditions (an extension; the paper has none): for each real
    #: condition C and each change K named here, a condition ``C~K`` of C's images with K applied
    #: (night, snow, cast, contrast; see fdnet.data.appearance). Empty: the real conditions only
    synthetic_conditions: tuple[str, ...] = ()
    #: with a validation pair, the ``synthetic_conditions`` settings the run chooses from, each
    #: written as changes joined by "+" ("night", "night+snow") or "none": every one is tried with
    #: every candidate trunk block (``model.backbone_block_candidates``) and the closed-form start
    #: that validates best is trained, as the block is chosen. ``synthetic_conditions`` must be
    #: among them: it is what a run without a validation pair uses. Empty: no choice
    synthetic_conditions_candidates: tuple[str, ...] = ()


def synthetic_option(text: str) -> tuple[str, ...]:
    """One ``data.synthetic_conditions_candidates`` entry -> its changes ("none" -> ())."""
    text = str(text).strip()
    return () if text in ("", "none") else tuple(part.strip() for part in text.split("+"))


def synthetic_option_text(changes) -> str:
    return "+".join(changes) or "none"


@dataclass
class ScheduleConfig:
    """Steps = mini-batches. The stages run one after the other (paper section 4.1)."""

    pretrain_autoencoder_steps: int = 5000
    pretrain_critic_steps: int = 8000
    joint_steps: int = 60000
    #: discriminator updates per encoder/decoder update in the joint stage (paper: 2)
    critic_updates_per_step: int = 2
    #: draw a new batch for every discriminator update of a joint step (else the updates of one
    #: step share one batch's content vectors and differ in the pairs drawn)
    critic_fresh_batches: bool = False
    #: Algorithm 1's batch use: each joint step samples ONE mini-batch X_b; the encoder/decoder
    #: update comes first, then the D_a updates, all on X_b (pairs drawn from X_b each time).
    #: False: the D_a updates take their own batch (or one each, critic_fresh_batches) before the
    #: encoder/decoder update takes another, which sees twice the images per step
    one_batch_per_step: bool = False


@dataclass
class LossConfig:
    """Weights of L_r, L_a and L_e^adv in the encoder/decoder objective (paper eq. 10 uses 1, 1, 1)."""

    reconstruction_weight: float = 1.0
    appearance_weight: float = 1.0
    adversarial_weight: float = 1.0
    triplet_margin: float = 0.1
    gradient_penalty_weight: float = 10.0
    #: include the triplet loss L_a while pretraining the auto-encoder (the paper's pretraining
    #: stage says "encoder and decoder"; L_a shapes the appearance encoder from the start)
    appearance_in_pretraining: bool = True
    #: L_r per image: "sum" = eq. 3's squared L2 norm ||x - x~||^2 summed over every value of the
    #: image (averaged over the batch); "mean" = the mean squared error per value. With eq. 10's
    #: weights 1/1/1 the choice sets the balance: at 224x224x3, "sum" makes L_r outweigh L_a
    #: about 54x at initialisation (the paper's balance), "mean" makes L_a outweigh L_r ~2800x
    reconstruction_reduction: str = "mean"
    #: vectors the triplet loss L_a compares: "raw" = v_a as the encoder outputs it (paper eq. 5);
    #: "l2" = unit v_a, so the fixed margin cannot be met just by conditions drifting apart in
    #: scale (with raw v_a the loss sat at 0 for most of a cpu-preset run)
    triplet_vectors: str = "raw"
    #: weight of L_s, which keeps the within-condition similarity structure of what the content
    #: encoder reads (an extension; 0 = off, as in the paper): the mean squared difference between
    #: the cosine similarities of v_c and of the encoder's centred, flattened input over pairs of
    #: images of one condition. L_e^adv is free to change how conditions relate; L_s asks it not to
    #: take out what tells places within a condition apart. Label-free: it uses condition labels only
    structure_weight: float = 0.0
    #: ablation switches (``fdnet reproduce --experiments ablation``; docs/runs.md says what each
    #: removes per preset). Unlike a weight of 0, False removes the part from every stage: it is
    #: never computed, never logged and nothing is stepped for it.
    #: ``adversarial``: no critic D_a and no L_e^adv: D_a is never updated (its weights stay as
    #: initialised), the critic pretraining stage is skipped (the run has
    #: schedule.pretrain_critic_steps fewer steps; the encoders/decoder get as many updates), and
    #: a joint step is one encoder/decoder update on L_r and L_a alone (L_s, which only acts with
    #: L_e^adv, is refused with it)
    adversarial: bool = True
    #: ``appearance_triplet``: no L_a in any stage; E_a then learns only through the decoder (L_r)
    appearance_triplet: bool = True
    #: ``reconstruction``: no L_r and no decoder pass in any stage (the decoder is never updated);
    #: the auto-encoder stage trains E_a on L_a alone, and is skipped when L_a is off there too
    reconstruction: bool = True


#: the ablation switches of :class:`LossConfig` (``loss.<name>``), in the order the docs list them
ABLATION_SWITCHES = ("adversarial", "appearance_triplet", "reconstruction")


@dataclass
class OptimConfig:
    #: Adam, paper: lr 1e-4, beta1 ("momentum") 0.5
    lr: float = 1e-4
    critic_lr: float = 1e-4
    #: multiplies the encoder/decoder learning rate in the joint stage
    joint_lr_scale: float = 1.0
    beta1: float = 0.5
    beta2: float = 0.999


@dataclass
class RuntimeConfig(SharedRuntimeConfig):
    """The ``runtime`` section every trained method has (seed, device, threads, bf16: autocast for
    the encoders/decoder, checkpoint_every, log_every; :class:`fdnet.methods.settings.RuntimeConfig`)
    with FDNet's defaults, plus FDNet's own settings."""

    checkpoint_every: int = 1000
    log_every: int = 10
    channels_last: bool = False
    #: BatchNorm/dropout mode of the content encoder when it computes vectors for a
    #: discriminator update: "train" (batch statistics, dropout on, as in the encoder's own
    #: update) or "eval" (running statistics, no dropout, as at test time)
    critic_encoder_mode: str = "train"


@dataclass
class FDNetRunConfig:
    preset: str = "paper"
    model: FDNetConfig = field(default_factory=FDNetConfig)
    data: FDNetDataConfig = field(default_factory=FDNetDataConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    validation: ValidationConfig = field(default_factory=ValidationConfig)

    @property
    def stage_steps(self) -> tuple[int, int, int]:
        """Steps the run takes in each stage (auto-encoder, critic, joint): the schedule's, less a
        stage the ablation switches leave with nothing to train (the critic stage without
        ``loss.adversarial``; the auto-encoder stage without L_r and without L_a there)."""
        s, loss = self.schedule, self.loss
        autoencoder = (
            s.pretrain_autoencoder_steps
            if (loss.reconstruction or (loss.appearance_triplet and loss.appearance_in_pretraining))
            else 0
        )
        critic = s.pretrain_critic_steps if loss.adversarial else 0
        return autoencoder, critic, s.joint_steps

    @property
    def total_steps(self) -> int:
        return sum(self.stage_steps)

    def with_total_steps(self, steps: int) -> "FDNetRunConfig":
        """``steps`` in all (``fdnet train --steps``): the joint stage takes what the pretraining
        stages leave."""
        s = self.schedule
        autoencoder, critic, _ = self.stage_steps
        pretraining = autoencoder + critic
        if steps < pretraining:
            raise ConfigError(
                f"--steps {steps}: FDNet's pretraining stages alone take {pretraining} steps "
                f"(schedule.pretrain_autoencoder_steps {s.pretrain_autoencoder_steps} + "
                f"schedule.pretrain_critic_steps {s.pretrain_critic_steps}); give more, or lower them "
                "with --set"
            )
        return dataclasses.replace(self, schedule=dataclasses.replace(s, joint_steps=int(steps) - pretraining))

    def stage_at(self, step: int) -> str:
        """Stage of (0-based) ``step``: "autoencoder", "critic" or "joint"."""
        autoencoder, critic, _ = self.stage_steps
        if step < autoencoder:
            return "autoencoder"
        if step < autoencoder + critic:
            return "critic"
        return "joint"

    def ablated(self) -> list[str]:
        """The parts the ablation switches remove, by switch name (empty for the full method)."""
        return [name for name in ABLATION_SWITCHES if not getattr(self.loss, name)]


def _paper() -> FDNetRunConfig:
    """The paper, setting by setting (section 4.1, eq. 3, eq. 10, Algorithm 1). Where the paper is
    silent the choice is marked: the number of encoding blocks and the decoder's first layer."""
    return FDNetRunConfig(
        preset="paper",
        # 224 / 2^5 = 7: five blocks leave a 7x7 map, as DCGAN-style encoders at 224 do (the
        # block count is not legible in the paper's Fig. 3). The critic reads v_c as the encoder
        # outputs it (section 3.3), not a normalised copy.
        model=FDNetConfig(
            input_size=(224, 224), widths=(64, 128, 256, 512, 512), vector_length=512, critic_input="raw"
        ),
        data=FDNetDataConfig(batch_per_domain=4),
        # 5000 auto-encoder + 8000 D_a pretraining steps, 60000 joint steps at 2 D_a updates per
        # encoder/decoder update, each joint step on one mini-batch (Algorithm 1).
        schedule=ScheduleConfig(5000, 8000, 60000, 2, one_batch_per_step=True),
        # Eq. 10 with weights 1, 1, 1 and eq. 3's summed squared error per image.
        loss=LossConfig(reconstruction_reduction="sum"),
        runtime=RuntimeConfig(checkpoint_every=2000, log_every=50),
    )


def _paper_native() -> FDNetRunConfig:
    """The paper's recipe (``paper``: schedule, Algorithm 1's batch use, optimiser, eq. 3/10's losses,
    the raw critic input) at Nordland's own 32x64 frames, sized to run to its end in a little over two
    hours on 2 idle CPU cores (measured 2.0-2.65 h, median 2.3 h): four encoding blocks of the
    paper's widths 64..512 (a 2x4 map; five, as ``paper`` has at 224, would leave 1x2 and took 3.6 h),
    bf16 autocast and channels_last, 2 torch threads. docs/runs.md has the measurements."""
    config = _paper()
    config.preset = "paper-native"
    config.model = FDNetConfig(input_size=(32, 64), widths=(64, 128, 256, 512), vector_length=512, critic_input="raw")
    config.runtime = RuntimeConfig(threads=2, bf16=True, channels_last=True, checkpoint_every=2000, log_every=50)
    config.validation = ValidationConfig(every=1000)
    return config


def _two_cores(
    name: str, model: FDNetConfig, schedule: ScheduleConfig, adversarial_weight: float = 0.1
) -> FDNetRunConfig:
    """What the CPU presets share: B = 8 per condition, a critic fed L2-normalised content vectors
    (docs/results.md, learnt 1), one torch thread (OpenMP spin-waiting against other processes on
    2 shared cores made steps ~6x slower), bf16 autocast and channels_last."""
    return FDNetRunConfig(
        preset=name,
        model=model,
        data=FDNetDataConfig(batch_per_domain=8),
        schedule=schedule,
        loss=LossConfig(adversarial_weight=adversarial_weight),
        runtime=RuntimeConfig(threads=1, bf16=True, channels_last=True, checkpoint_every=250, log_every=10),
    )


def _cpu() -> FDNetRunConfig:
    # FDNet on a frozen ImageNet trunk (model.backbone; an extension, see fdnet.methods.fdnet.trunk):
    # from scratch, the paper's pixel encoders did not beat SAD on Gardens Point's 100 training
    # images per condition (cpu-scratch below; docs/results.md, gp2-gp7). 128x256 keeps
    # Nordland's 1:2 aspect. Block 7 is a stride-16 map (80 x 8 x 16), block 11 a deeper
    # stride-32 one (192 x 4 x 8). With a validation pair a run starts on whichever validates better
    # (backbone_block_candidates): no one depth suits every route (with the mined-pair start,
    # Nordland held-out validation 0.92 for block 7 against 0.87 for 11; Gardens Point 0.90 for
    # block 11 against 0.84 for 7 and 0.88 for 14; docs/results.md). Without
    # one, block 7. The trunk's maps are computed once per run and candidate block.
    #
    # E_c is the projection head (content_head=trunk_projection): the trunk's map projected to
    # L = 512, starting in closed form from pairs of frames mined across the training conditions
    # (projection_init=mined_pairs, fdnet.methods.fdnet.content_fit); L_e^adv then trains an L x L
    # refinement of it, so its weight only scales the head's step (Adam): 1, as in eq. 10.
    config = _two_cores(
        "cpu",
        FDNetConfig(
            input_size=(128, 256),
            widths=(128, 256),
            vector_length=512,
            critic_hidden=512,
            input_norm="per_image",
            critic_input="l2",
            backbone="efficientnet-lite0",
            backbone_block=7,
            backbone_block_candidates=(7, 11),
            content_head="trunk_projection",
            projection_init="mined_pairs",
        ),
        # 500 auto-encoder steps shape E_a and the decoder, 200 critic steps, then 300 joint steps:
        # in the measured runs (docs/results.md) the joint stage did not raise validation
        # R@1 beyond its start (Nordland 0.91 -> 0.83 by step 1000), and step 1000 is what fits in
        # about 20 minutes on 2 cores; best/ keeps the best-validating checkpoint.
        ScheduleConfig(
            pretrain_autoencoder_steps=500, pretrain_critic_steps=200, joint_steps=300, critic_updates_per_step=2
        ),
        adversarial_weight=1.0,
    )
    # With a validation pair the run also chooses whether to add a synthetic night copy of every
    # condition: the mined pairs then include exact (image, its night copy) pairs that teach the
    # whitening what a night change does. It validates better on Gardens Point (night) and on
    # Nordland with held-out validation frames, and is the same or worse on validation frames
    # inside the mined range (docs/results.md).
    config.data.synthetic_conditions_candidates = ("none", "night")
    return config


def _cpu_scratch() -> FDNetRunConfig:
    # The paper's architecture (pixel encoders learnt from scratch), sized for 2 CPU cores:
    # quarter-width blocks (16..128) are several times cheaper than 64..512, and 64x32 is
    # Nordland's native size. Per-image standardisation: nord5 in docs/results.md (R@1 0.306 vs
    # 0.269 with [-1, 1] input on Nordland's test frames).
    return _two_cores(
        "cpu-scratch",
        FDNetConfig(
            input_size=(32, 64),
            widths=(16, 32, 64, 128),
            vector_length=512,
            critic_hidden=512,
            input_norm="per_image",
            critic_input="l2",
        ),
        ScheduleConfig(
            pretrain_autoencoder_steps=1000, pretrain_critic_steps=200, joint_steps=1000, critic_updates_per_step=2
        ),
    )


def _tiny() -> FDNetRunConfig:
    return FDNetRunConfig(
        preset="tiny",
        model=FDNetConfig(input_size=(16, 32), widths=(8, 16), vector_length=16, critic_hidden=16),
        data=FDNetDataConfig(batch_per_domain=2),
        schedule=ScheduleConfig(
            pretrain_autoencoder_steps=3, pretrain_critic_steps=2, joint_steps=3, critic_updates_per_step=2
        ),
        runtime=RuntimeConfig(threads=1, checkpoint_every=4, log_every=1),
        validation=ValidationConfig(every=4),
    )


PRESETS = {"paper": _paper, "paper-native": _paper_native, "cpu": _cpu, "cpu-scratch": _cpu_scratch, "tiny": _tiny}


def preset(name: str) -> FDNetRunConfig:
    try:
        return PRESETS[name]()
    except KeyError as exc:
        raise ConfigError(f"unknown preset {name!r}; available: {', '.join(PRESETS)}") from exc


def validate(config: FDNetRunConfig) -> None:
    """Every check that does not need the data: raise ConfigError before anything is built."""
    validate_architecture(config.model)
    s = config.schedule
    for name in ("pretrain_autoencoder_steps", "pretrain_critic_steps", "joint_steps"):
        if getattr(s, name) < 0:
            raise ConfigError(f"schedule.{name} must be >= 0, got {getattr(s, name)}")
    if s.critic_updates_per_step < 0:
        raise ConfigError(f"schedule.critic_updates_per_step must be >= 0, got {s.critic_updates_per_step}")
    from fdnet.data.appearance import check_changes

    check_changes(list(config.data.synthetic_conditions))
    options = [synthetic_option(text) for text in config.data.synthetic_conditions_candidates]
    for option in options:
        try:
            check_changes(list(option))
        except ConfigError as exc:
            raise ConfigError(f"data.synthetic_conditions_candidates: {synthetic_option_text(option)}: {exc}") from exc
    if options:
        if len(set(options)) != len(options):
            raise ConfigError(
                "data.synthetic_conditions_candidates: "
                f"{list(config.data.synthetic_conditions_candidates)} names a setting twice"
            )
        if tuple(config.data.synthetic_conditions) not in options:
            raise ConfigError(
                f"data.synthetic_conditions={list(config.data.synthetic_conditions)} is not among "
                f"data.synthetic_conditions_candidates={list(config.data.synthetic_conditions_candidates)} "
                "(it is what a run without a validation pair uses); add it, or set "
                "data.synthetic_conditions_candidates=[]"
            )
        if config.model.content_head not in ("trunk_residual", "trunk_projection"):
            raise ConfigError(
                "data.synthetic_conditions_candidates: choosing needs model.content_head=trunk_residual "
                "or trunk_projection (it scores the head's closed-form start); set "
                "data.synthetic_conditions_candidates=[] to use data.synthetic_conditions alone"
            )
    if config.data.batch_per_domain < 2:
        raise ConfigError(f"data.batch_per_domain must be >= 2, got {config.data.batch_per_domain}")
    if config.runtime.critic_encoder_mode not in ("train", "eval"):
        raise ConfigError(f"runtime.critic_encoder_mode: {config.runtime.critic_encoder_mode!r}; choose train or eval")
    from fdnet.backbones import check_device_spec

    check_device_spec(config.runtime.device, where="runtime.device")
    for name in ("checkpoint_every", "log_every"):
        if getattr(config.runtime, name) <= 0:
            raise ConfigError(f"runtime.{name} must be >= 1")
    v = config.validation
    check_validation_pair(v)
    if v.reference and v.every <= 0:
        raise ConfigError("validation.every must be >= 1")
    if config.loss.triplet_margin < 0 or config.loss.gradient_penalty_weight < 0:
        raise ConfigError("loss.triplet_margin and loss.gradient_penalty_weight must be >= 0")
    if config.loss.reconstruction_reduction not in ("mean", "sum"):
        raise ConfigError(
            f"loss.reconstruction_reduction: {config.loss.reconstruction_reduction!r}; " "choose mean or sum"
        )
    if config.loss.triplet_vectors not in ("raw", "l2"):
        raise ConfigError(f"loss.triplet_vectors: {config.loss.triplet_vectors!r}; choose raw or l2")
    for name in ("lr", "critic_lr", "joint_lr_scale", "beta1", "beta2"):
        check_finite(
            f"optim.{name}", getattr(config.optim, name), positive=name in ("lr", "critic_lr", "joint_lr_scale")
        )
    for name in (
        "reconstruction_weight",
        "appearance_weight",
        "adversarial_weight",
        "triplet_margin",
        "gradient_penalty_weight",
        "structure_weight",
    ):
        check_finite(f"loss.{name}", getattr(config.loss, name))
    if not (config.loss.adversarial or config.loss.appearance_triplet or config.loss.reconstruction):
        raise ConfigError(
            "loss.adversarial, loss.appearance_triplet and loss.reconstruction are all false: "
            "nothing would be trained; keep at least one"
        )
    if not config.loss.adversarial and config.loss.structure_weight > 0:
        raise ConfigError(
            "loss.structure_weight > 0 needs loss.adversarial=true (L_s only acts beside L_e^adv); "
            "set loss.structure_weight=0 to train without the critic"
        )
    if not (0.0 <= config.optim.beta1 < 1.0 and 0.0 <= config.optim.beta2 < 1.0):
        raise ConfigError(f"optim.beta1/beta2 must lie in [0, 1), got {config.optim.beta1}, {config.optim.beta2}")


__all__ = [
    "ABLATION_SWITCHES",
    "FDNetRunConfig",
    "FDNetDataConfig",
    "DataConfig",
    "ScheduleConfig",
    "LossConfig",
    "OptimConfig",
    "RuntimeConfig",
    "ValidationConfig",
    "PRESETS",
    "preset",
    "apply_yaml",
    "validate",
    "to_dict",
]
