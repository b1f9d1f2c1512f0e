"""FDNet: content encoder, appearance encoder, decoder and pairwise appearance discriminator.

Qin et al., "Appearance-invariant place recognition by adversarially learning disentangled
representation" (sections 3 and 4.1). ``FDNetConfig`` holds every architecture setting; where
the paper is silent the choice is documented on the field and can be changed.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import nn

from fdnet.backbones import block_channels
from fdnet.errors import ConfigError
from fdnet.methods.fdnet.decoder import Decoder
from fdnet.methods.fdnet.discriminator import PairDiscriminator
from fdnet.methods.fdnet.encoder import Encoder
from fdnet.methods.fdnet.trunk import BACKBONES, FrozenTrunk, trunk_map_size, trunk_stride

INPUT_NORMS = ("none", "per_image", "per_patch")
CRITIC_INPUTS = ("l2", "raw")
CONTENT_HEADS = ("encoder", "trunk_residual", "trunk_projection")
PROJECTION_INITS = ("pca", "mined_pairs")
TRUNK_HEADS = ("trunk_residual", "trunk_projection")


@dataclass
class FDNetConfig:
    #: (height, width) the images are resized to; each must be divisible by 2 ** len(widths)
    input_size: tuple[int, int] = (224, 224)
    #: output channels of the encoding blocks (one block each); the decoder mirrors them.
    #: The paper's Fig. 3 is not legible on block count; 4 blocks of 64..512 is DCGAN's layout.
    #: With a backbone it may be empty: E_c and E_a are then one linear layer on the trunk's map
    #: (at N(0, 0.02) initialisation a Gaussian random projection of it, i.e. Conv3 + GRP).
    widths: tuple[int, ...] = (64, 128, 256, 512)
    #: L, the length of the content and appearance vectors (paper: 256/512/1024/2048)
    vector_length: int = 512
    encoder_dropout: float = 0.5
    critic_hidden: int = 512
    critic_dropout: float = 0.25
    #: what the encoders see: "none" = RGB scaled to [-1, 1] (decoder output tanh);
    #: "per_image" = each image standardised to zero mean, unit variance (decoder output linear),
    #: which removes global brightness/contrast; "per_patch" = each non-overlapping
    #: ``patch_size`` x ``patch_size`` patch standardised on its own, SeqSLAM's patch normalisation
    #: (Milford & Wyeth 2012), which also removes local illumination (night, shadows)
    input_norm: str = "none"
    #: patch side for input_norm "per_patch" (input height and width must be multiples of it)
    patch_size: int = 8
    #: floor of the standard deviation an image (per_image) or patch (per_patch) is divided by;
    #: None = 0.02 for per_image, 0.005 for per_patch. Lower = near-black frames (tunnels)
    #: become amplified sensor noise instead of one flat image
    min_std: float | None = None
    #: what D_a sees: "l2" = L2-normalised content vectors (the descriptor is compared by cosine,
    #: so only the direction matters; an unnormalised v_c lets the encoder fool the critic by
    #: scaling), "raw" = the encoder output as the paper's text implies
    critic_input: str = "l2"
    #: "none" = the paper's encoders on pixels; "efficientnet-lite0" (or the larger -lite1 and
    #: -lite2) = a frozen ImageNet trunk in front of both encoders, whose map they encode and the
    #: decoder reconstructs (an extension for small training sets, see
    #: :mod:`fdnet.methods.fdnet.trunk`); input_size is then the image size given to the trunk, and
    #: input_norm applies to the trunk's map ("none" or "per_image")
    backbone: str = "none"
    #: with a backbone: its last block used (EfficientNet-Lite0: 4 = 40 ch at stride 8,
    #: 7 = 80 ch at stride 16, the conv3-like map; each backbone's table: :mod:`fdnet.backbones`)
    backbone_block: int = 7
    #: with a backbone, the residual content head and a validation pair: the trunk blocks a fresh
    #: run chooses ``backbone_block`` from before it trains. Each candidate's closed-form content
    #: start (the residual head after its data-dependent start, no gradient step) is scored on
    #: the validation pair as checkpoints are for ``best/`` (R@1, ties to AUC), and the best one
    #: is trained; the scores are kept in the checkpoints' state. Which depth keeps the place
    #: depends on the data: a fine stride-16 map for Nordland's 64x32 frames seen 10 s apart, a
    #: coarse stride-32 map for Gardens Point's hand-held walk (docs/results.md). ()
    #: or no validation pair: ``backbone_block`` alone, which must be one of the candidates
    backbone_block_candidates: tuple[int, ...] = ()
    #: E_c: "encoder" = the paper's (encoding blocks + a fully connected layer to L);
    #: "trunk_residual" (needs a backbone) = the trunk's flattened map, centred on the training
    #: maps' mean, minus a learnt rank-``residual_rank`` part: v_c = x - U V^T x. U starts at
    #: zero, so training starts exactly at the trunk's descriptor and can only remove what the
    #: adversarial critic finds condition-specific; v_c then has the map's length, not L
    content_head: str = "encoder"
    #: rank of the removable part of the trunk_residual head
    residual_rank: int = 32
    #: where the trunk_residual head starts: "zero" (U = 0: the centred trunk descriptor) or
    #: "condition_means" (the directions between the training conditions' mean maps already
    #: removed; a closed form of what the critic looks for, computed from the same condition
    #: labels FDNet trains with, no place labels); the adversarial stage refines either
    residual_init: str = "zero"
    #: "trunk_projection" (needs a backbone): v_c = (x - mean) P, x the trunk's flattened map and P
    #: a (map length x L) projection, so v_c has the paper's length L (``vector_length``). P starts
    #: in closed form (:mod:`fdnet.methods.fdnet.content_fit`): "pca" = the condition-mean
    #: directions removed, then PCA scaled by eigenvalue ** -projection_pca_power; "mined_pairs" =
    #: that start, then the learnt whitening of the pairs of frames it matches mutually across
    #: conditions (sequence-consistent over ``pair_sequence_length`` frames of each traverse; no
    #: cross-condition labels). The adversarial stage then trains an L x L refinement R of the start
    #: (:class:`TrunkProjectionContent`), as it moves the residual head's U
    projection_init: str = "mined_pairs"
    #: principal directions kept before the mined-pair whitening (at most one fewer than the images)
    projection_pca_dims: int = 1024
    #: the start's coordinate k is divided by eigenvalue_k ** projection_pca_power (0 = PCA, 0.5 =
    #: full whitening; 0.25 validated best, docs/results.md)
    projection_pca_power: float = 0.25
    #: frames of each traverse a mined pair's sequence similarity runs over
    pair_sequence_length: int = 5
    #: shrinkage of the pairs' difference covariance towards its mean eigenvalue (x its trace / dims)
    pair_shrinkage: float = 1.0

    def encoder_input_size(self) -> tuple[int, int]:
        """(H, W) of what the encoders read: the image, or the trunk's map of it."""
        if self.backbone == "none":
            return tuple(int(v) for v in self.input_size)
        return trunk_map_size(self.input_size, self.backbone_block, self.backbone)


#: the most weights one layer may have: 4e8 float32 weights are 1.6 GB, about 6.4 GB with their
#: gradient and Adam's two moments. A shallow trunk block at a large input makes the decoder's first
#: layer (flattened map to flattened map) grow with the square of the map: block 0 at 128x256
#: would be 1.7e10 weights, which fails in the allocator after minutes of loading images.
MAX_LAYER_WEIGHTS = 400_000_000


def largest_layer_weights(config: FDNetConfig) -> int:
    """Weights in the largest fully connected layer the config builds (the decoder's first layer,
    or the critic's first layer on a pair of content vectors)."""
    height, width = config.encoder_input_size()
    channels = 3 if config.backbone == "none" else block_channels(config.backbone, int(config.backbone_block))
    map_values = channels * height * width
    content = map_values if config.content_head == "trunk_residual" else int(config.vector_length)
    scale = 2 ** len(config.widths)
    decoder_out = (int(config.widths[-1]) * (height // scale) * (width // scale)) if config.widths else map_values
    decoder = (content + int(config.vector_length)) * decoder_out
    critic = 2 * content * int(config.critic_hidden)
    # (the projection head's start is a buffer, never trained: it has no gradient or Adam moments)
    return max(decoder, critic)


def validate_architecture(config: FDNetConfig) -> None:
    """Raise ConfigError for settings the architecture cannot take (before building anything)."""
    height, width = _check_sizes(config)
    if config.input_norm not in INPUT_NORMS:
        raise ConfigError(f"model.input_norm: {config.input_norm!r}; choose one of {', '.join(INPUT_NORMS)}")
    if config.input_norm == "per_patch" and (
        config.patch_size <= 0 or height % config.patch_size or width % config.patch_size
    ):
        raise ConfigError(f"model.patch_size: {config.patch_size} must divide the input size {height}x{width}")
    _check_block_candidates(config)
    _check_content_head(config, height, width)
    if config.critic_input not in CRITIC_INPUTS:
        raise ConfigError(f"model.critic_input: {config.critic_input!r}; choose one of {', '.join(CRITIC_INPUTS)}")
    for name in ("encoder_dropout", "critic_dropout"):
        if not 0.0 <= getattr(config, name) < 1.0:
            raise ConfigError(f"model.{name}: must be in [0, 1), got {getattr(config, name)}")


def _check_sizes(config: FDNetConfig) -> tuple[int, int]:
    """The input size, blocks and backbone must fit together (strides, the largest layer's
    weights); returns (height, width)."""
    if len(config.input_size) != 2:
        raise ConfigError(f"model.input_size: expected (height, width), got {config.input_size!r}")
    if not config.widths and config.backbone == "none":
        raise ConfigError("model.widths: need at least one encoding block (zero blocks only with a model.backbone)")
    if any(w <= 0 for w in config.widths):
        raise ConfigError(f"model.widths: channel widths must be positive, got {list(config.widths)}")
    if config.vector_length <= 0:
        raise ConfigError(f"model.vector_length: must be positive, got {config.vector_length}")
    if config.backbone not in BACKBONES:
        raise ConfigError(f"model.backbone: {config.backbone!r}; choose one of {', '.join(BACKBONES)}")
    scale = 2 ** len(config.widths)
    height, width = (int(v) for v in config.input_size)
    if config.backbone != "none":
        if config.input_norm == "per_patch":
            raise ConfigError(
                f"model.input_norm: per_patch cannot be used with model.backbone={config.backbone} "
                "(it normalises pixel patches; the trunk sees the image as on ImageNet); "
                "use none or per_image (which standardises the trunk's map)"
            )
        stride = trunk_stride(config.backbone_block, config.backbone)
        scale *= stride
    for name, value in (("height", height), ("width", width)):
        if value < scale or value % scale:
            raise ConfigError(
                f"model.input_size: {name} {value} cannot go through {len(config.widths)} stride-2 blocks"
                + (f" after the backbone's stride {stride}" if config.backbone != "none" else "")
                + "; it must be a positive multiple of "
                + (f"{stride} x " if config.backbone != "none" else "")
                + f"2^{len(config.widths)} = {scale} "
                f"(e.g. {max(scale, round(value / scale) * scale)}), or use fewer blocks (model.widths)"
            )
    weights = largest_layer_weights(config)
    if weights > MAX_LAYER_WEIGHTS:
        raise ConfigError(
            f"model: this architecture's largest layer would have {weights:.2e} weights ({weights * 16 / 1e9:.0f} GB "
            f"with gradients and Adam's moments; at most {MAX_LAYER_WEIGHTS:.0e}): the flattened "
            + (f"trunk map of block {config.backbone_block} " if config.backbone != "none" else "input ")
            + f"at {height}x{width} is too long; use a deeper model.backbone_block, a smaller model.input_size "
            "or more model.widths"
        )
    return height, width


def _check_block_candidates(config: FDNetConfig) -> None:
    """The trunk blocks a run may choose among: each one a valid architecture."""
    if not config.backbone_block_candidates:
        return
    candidates = [int(b) for b in config.backbone_block_candidates]
    if config.backbone == "none" or config.content_head not in TRUNK_HEADS:
        raise ConfigError(
            "model.backbone_block_candidates: choosing a trunk block needs model.backbone and "
            "model.content_head=trunk_residual or trunk_projection (it scores the head's "
            "closed-form start); "
            "set model.backbone_block_candidates=[] to use model.backbone_block alone"
        )
    if config.backbone_block not in candidates:
        raise ConfigError(
            f"model.backbone_block={config.backbone_block} is not among "
            f"model.backbone_block_candidates={candidates} (it is the block used without a "
            "validation pair); add it, or set model.backbone_block_candidates=[] to use it alone"
        )
    if len(set(candidates)) != len(candidates):
        raise ConfigError(f"model.backbone_block_candidates: {candidates} names a block twice")
    for block in candidates:
        if block != config.backbone_block:
            try:
                validate_architecture(dataclasses.replace(config, backbone_block=block, backbone_block_candidates=()))
            except ConfigError as exc:
                raise ConfigError(f"model.backbone_block_candidates: block {block}: {exc}") from exc


def _check_content_head(config: FDNetConfig, height: int, width: int) -> None:
    """The content head and its own settings."""
    if config.content_head not in CONTENT_HEADS:
        raise ConfigError(f"model.content_head: {config.content_head!r}; choose one of {', '.join(CONTENT_HEADS)}")
    if config.content_head == "trunk_residual":
        if config.backbone == "none":
            raise ConfigError("model.content_head=trunk_residual needs a model.backbone (it starts at the trunk's map)")
        if config.residual_rank < 1:
            raise ConfigError(f"model.residual_rank: must be >= 1, got {config.residual_rank}")
        if config.residual_init not in ("zero", "condition_means"):
            raise ConfigError(f"model.residual_init: {config.residual_init!r}; choose zero or condition_means")
    if config.content_head == "trunk_projection":
        if config.backbone == "none":
            raise ConfigError(
                "model.content_head=trunk_projection needs a model.backbone " "(it projects the trunk's map)"
            )
        if config.projection_init not in PROJECTION_INITS:
            raise ConfigError(
                f"model.projection_init: {config.projection_init!r}; choose one of " f"{', '.join(PROJECTION_INITS)}"
            )
        channels = block_channels(config.backbone, int(config.backbone_block))
        map_length = channels * height * width // trunk_stride(config.backbone_block, config.backbone) ** 2
        if config.vector_length > map_length:
            raise ConfigError(
                f"model.vector_length: L = {config.vector_length} is longer than the trunk map it "
                f"projects ({map_length} values at block {config.backbone_block}, {height}x{width}); "
                "lower L or use a larger model.input_size"
            )
        if config.projection_pca_dims < 1 or config.pair_sequence_length < 1:
            raise ConfigError("model.projection_pca_dims and model.pair_sequence_length must be >= 1")
        if not (0 <= config.projection_pca_power <= 1) or not (config.pair_shrinkage >= 0):
            raise ConfigError(
                f"model.projection_pca_power must lie in [0, 1] and model.pair_shrinkage be >= 0, "
                f"got {config.projection_pca_power}, {config.pair_shrinkage}"
            )


def init_weights(module: nn.Module) -> None:
    """Paper: all weights from N(0, 0.02). BatchNorm scales from N(1, 0.02) and biases zero, as
    in DCGAN (Radford et al. 2016), whose initialisation the paper's value comes from."""
    if isinstance(module, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear)):
        nn.init.normal_(module.weight, 0.0, 0.02)
        if module.bias is not None:
            nn.init.zeros_(module.bias)
    elif isinstance(module, (nn.BatchNorm1d, nn.BatchNorm2d)):
        nn.init.normal_(module.weight, 1.0, 0.02)
        nn.init.zeros_(module.bias)


class TrunkResidualContent(nn.Module):
    """E_c as the trunk's descriptor minus a learnt low-rank part: v_c = x - U (V^T x), with
    x = flatten(map) - mean. ``mean`` (a buffer, saved with the weights) is set once from the
    training maps (:meth:`set_mean`); U starts at zero, so the untrained head is exactly the
    centred trunk descriptor. A rank-r correction can take at most r directions out of a
    ~10^4-d map, so the adversarial game cannot destroy the place information the trunk has; it
    can only remove the directions that tell conditions apart (e.g. the difference of the
    conditions' mean maps, worth +0.09 R@1 on Nordland's validation frames in closed form).
    L_r does not train it (the decoder reads a detached v_c): the head keeps the trunk's
    information by construction, and reconstruction gradients would only move U at random."""

    def __init__(self, feature_shape: tuple[int, int, int], rank: int) -> None:
        super().__init__()
        length = int(feature_shape[0] * feature_shape[1] * feature_shape[2])
        self.vector_length = length
        self.register_buffer("mean", torch.zeros(length))
        self.u = nn.Parameter(torch.zeros(length, rank))
        self.v = nn.Parameter(torch.empty(length, rank))
        nn.init.orthogonal_(self.v)

    @torch.no_grad()
    def set_mean(self, maps: torch.Tensor) -> None:
        self.mean.copy_(maps.float().flatten(1).mean(0))

    @torch.no_grad()
    def remove_condition_means(self, maps_per_condition: list[torch.Tensor]) -> int:
        """Start with the directions between the conditions' mean maps removed (U = V = their
        orthonormal basis in the first columns); returns how many directions that is."""
        means = torch.stack([m.float().flatten(1).mean(0) for m in maps_per_condition])
        spread = (means - means.mean(0)).T  # (length, conditions)
        basis, singular, _ = torch.linalg.svd(spread, full_matrices=False)
        keep = int((singular > singular.max() * 1e-6).sum()) if singular.numel() else 0
        keep = min(keep, self.u.shape[1])
        self.u[:, :keep] = basis[:, :keep]
        self.v[:, :keep] = basis[:, :keep]
        return keep

    def centred(self, maps: torch.Tensor) -> torch.Tensor:
        """x: the flattened maps minus the training maps' mean, where the head starts (U = 0)."""
        return maps.flatten(1).float() - self.mean

    def forward(self, maps: torch.Tensor) -> torch.Tensor:
        x = self.centred(maps)
        return x - (x @ self.v) @ self.u.T


class TrunkProjectionContent(nn.Module):
    """E_c as a linear projection of the trunk's flattened map to L: v_c = ((x - mean) P0)(I + R).
    ``mean`` and the start P0 (buffers, saved with the weights) come from the training maps in
    closed form (:meth:`set_start`, :mod:`fdnet.methods.fdnet.content_fit`); training moves only
    R (L x L, zero at the start), a refinement within the start's own coordinates. Adam's steps
    are about the learning rate per weight whatever a weight's scale: on P0's entries (~1e-3 for a
    10^4-long map) they wiped the start out within a few hundred steps (Gardens Point validation
    R@1 0.88 -> 0.60), on R's (coordinates of unit scale) they are a small change."""

    def __init__(self, feature_shape: tuple[int, int, int], length: int) -> None:
        super().__init__()
        size = int(feature_shape[0] * feature_shape[1] * feature_shape[2])
        self.vector_length = int(length)
        self.register_buffer("mean", torch.zeros(size))
        start = torch.empty(size, int(length))
        nn.init.orthogonal_(start)
        self.register_buffer("start", start)
        self.refine = nn.Parameter(torch.zeros(int(length), int(length)))

    @torch.no_grad()
    def set_start(self, mean, projection) -> None:
        self.mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        self.start.copy_(torch.as_tensor(projection, dtype=torch.float32))
        self.refine.zero_()

    def centred(self, maps: torch.Tensor) -> torch.Tensor:
        return maps.flatten(1).float() - self.mean

    def forward(self, maps: torch.Tensor) -> torch.Tensor:
        projected = self.centred(maps) @ self.start
        return projected + projected @ self.refine


class FDNet(nn.Module):
    """The four networks of FDNet, with the preprocessing they share.

    ``forward`` is not defined: training uses the parts (see ``fdnet.methods.fdnet.training``) and
    inference uses :meth:`content` (the place descriptor, paper section 4.2).
    """

    def __init__(self, config: FDNetConfig) -> None:
        super().__init__()
        validate_architecture(config)
        self.config = config
        size, widths, length = config.encoder_input_size(), tuple(config.widths), config.vector_length
        trunk = None if config.backbone == "none" else FrozenTrunk(config.backbone_block, config.backbone)
        channels = 3 if trunk is None else trunk.channels
        self.appearance_encoder = Encoder(size, widths, length, config.encoder_dropout, in_channels=channels)
        if config.content_head == "trunk_residual":
            self.content_encoder = TrunkResidualContent((channels, *size), config.residual_rank)
            content_length = self.content_encoder.vector_length
        elif config.content_head == "trunk_projection":
            self.content_encoder = TrunkProjectionContent((channels, *size), length)
            content_length = length
        else:
            self.content_encoder = Encoder(size, widths, length, config.encoder_dropout, in_channels=channels)
            content_length = length
        self.content_length = content_length
        # The decoder reconstructs exactly what the encoders see: [-1, 1] pixels (tanh), or
        # standardised pixels / trunk maps (linear).
        output = "tanh" if config.input_norm == "none" and trunk is None else "none"
        self.decoder = Decoder(
            size, widths, length, out_channels=channels, output=output, content_length=content_length
        )
        self.discriminator = PairDiscriminator(content_length, config.critic_hidden, config.critic_dropout)
        # N(0, 0.02) everywhere except the residual head, whose zero U / orthogonal V make it
        # start at the trunk's descriptor.
        for module in (self.appearance_encoder, self.decoder, self.discriminator):
            module.apply(init_weights)
        if isinstance(self.content_encoder, Encoder):
            self.content_encoder.apply(init_weights)
        # Attached after init_weights, which would overwrite its ImageNet weights. Not in
        # named_parts(): run directories hold only what training changed.
        self.trunk = trunk

    def named_parts(self) -> dict[str, nn.Module]:
        """The modules saved in a run directory, by name."""
        return {
            "content_encoder": self.content_encoder,
            "appearance_encoder": self.appearance_encoder,
            "decoder": self.decoder,
            "discriminator": self.discriminator,
        }

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) in [0, 1] -> what the encoders see and the decoder reconstructs: the image
        (or, with a backbone, the trunk's map of it) after ``input_norm``."""
        x = images if self.trunk is None else self.trunk(images)
        if self.config.input_norm == "per_image":
            mean = x.mean(dim=(1, 2, 3), keepdim=True)
            std = x.std(dim=(1, 2, 3), keepdim=True)
            # The floor keeps near-black frames (tunnels) from turning pixel noise into contrast.
            floor = 0.02 if self.config.min_std is None else self.config.min_std
            return (x - mean) / std.clamp_min(floor)
        if self.config.input_norm == "per_patch":
            n, c, h, w = x.shape
            p = self.config.patch_size
            patches = x.reshape(n, c, h // p, p, w // p, p)
            mean = patches.mean(dim=(1, 3, 5), keepdim=True)
            std = patches.std(dim=(1, 3, 5), keepdim=True)
            # A low floor: night patches have little contrast and it is exactly what must be kept.
            floor = 0.005 if self.config.min_std is None else self.config.min_std
            return ((patches - mean) / std.clamp_min(floor)).reshape(n, c, h, w)
        return x * 2.0 - 1.0 if self.trunk is None else x

    def critic_features(self, content: torch.Tensor) -> torch.Tensor:
        if self.config.critic_input == "l2":
            return nn.functional.normalize(content, dim=1)
        return content

    def content(self, images: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) in [0, 1] -> (N, L) content vectors v_c (not normalised)."""
        return self.content_encoder(self.preprocess(images))

    def appearance(self, images: torch.Tensor) -> torch.Tensor:
        return self.appearance_encoder(self.preprocess(images))
