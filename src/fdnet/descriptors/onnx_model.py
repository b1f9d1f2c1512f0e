"""Any ONNX model that maps images to vectors as a descriptor: ``--method onnx --weights MODEL.onnx``.

The best place descriptors of the day (MegaLoc, BoQ, SALAD, ...) live in their own projects and
travel as ONNX files; run through onnxruntime here, each serves every fdnet command after the
descriptor. The model takes one image batch, float (N, 3, H, W) (or (N, H, W, 3)) and returns
(N, D) vectors. How images are prepared is a setting (``--method-set KEY=VALUE``), read from the
model's metadata when it carries them (``fdnet export`` writes them; keys ``fdnet.input_size``
etc., or the bare names), and from the graph where it is fixed:

* ``input_size``: ``HxW`` (or ``[H, W]``); the graph's own when it is fixed, else required;
* ``mean``, ``std``: per channel, applied to RGB in [0, 1] (default 0 and 1: the model gets
  [0, 1]; ImageNet models usually want mean=[0.485,0.456,0.406] std=[0.229,0.224,0.225]);
* ``channels``: ``rgb`` (default) or ``bgr``; ``normalise``: ``l2`` (default) or ``none``;
* ``output``: which graph output holds the vectors (default the first);
* ``layout``: ``nchw`` or ``nhwc``, only where the graph does not say which axis holds the 3
  channels (both could, or neither is fixed): then (N, 3, H, W) with a warning unless given.

Every error names the model file. A ``mean`` outside [0, 1] or a ``std`` above 1 is refused:
those are values on the 0..255 scale (fdnet's images are in [0, 1]; divide them by 255).

Runs on the CPU, or CUDA when onnxruntime has its CUDA provider (``--device``). The model is
loaded from its path: weights stored as external data (``w.data``) are read beside the model, a
location outside the model's folder is refused. The fingerprint covers the model's bytes, the
bytes of its external data files and these settings, so a database or calibration made with one model
refuses another.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Sequence

import numpy as np

from fdnet.descriptors.base import Descriptor, check_vectors, l2_normalize
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import ConfigError, DataError, NotAvailableError

logger = logging.getLogger(__name__)

CHANNEL_CHOICES = ("rgb", "bgr")
NORMALISE_CHOICES = ("l2", "none")
LAYOUT_CHOICES = ("nchw", "nhwc")
#: model metadata keys (``fdnet.KEY`` or ``KEY``) that give a setting
METADATA_SETTINGS = ("input_size", "mean", "std", "channels", "normalise", "output", "layout")


def _parse_size(value, where: str) -> tuple[int, int]:
    from fdnet.data.images import check_image_size

    if isinstance(value, str):
        text = value.lower().replace(" ", "")
        if text.startswith("["):
            try:
                value = json.loads(text)
            except ValueError as exc:
                raise ConfigError(f"{where}: {value!r} is not HxW (e.g. 224x224)") from exc
        else:
            parts = text.split("x")
            if len(parts) != 2 or not all(p.isdigit() for p in parts):
                raise ConfigError(f"{where}: {value!r} is not HxW (e.g. 224x224)")
            value = [int(p) for p in parts]
    return check_image_size(value, where)


def _parse_triple(value, where: str) -> np.ndarray:
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except ValueError as exc:
            raise ConfigError(f"{where}: {value!r} is not a number or a list of 3 numbers") from exc
    array = np.asarray(value, dtype=np.float64).reshape(-1) if not isinstance(value, bool) else np.array([])
    if array.size == 1:
        array = np.repeat(array, 3)
    if array.size != 3 or not np.isfinite(array).all():
        raise ConfigError(f"{where}: {value!r} is not a number or a list of 3 numbers")
    return array.astype(np.float32)


def _providers(device: str | None) -> list[str]:
    import onnxruntime

    available = onnxruntime.get_available_providers()
    spec = (device or "auto").lower()
    if spec == "cpu":
        return ["CPUExecutionProvider"]
    if spec == "auto":
        return (["CUDAExecutionProvider"] if "CUDAExecutionProvider" in available else []) + ["CPUExecutionProvider"]
    if spec == "cuda" or spec.startswith("cuda:"):
        if "CUDAExecutionProvider" not in available:
            raise ConfigError(
                f"--device {device}: this onnxruntime has no CUDA provider (it has "
                f"{', '.join(available)}); install onnxruntime-gpu, or give --device cpu"
            )
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    from fdnet.backbones import check_device_spec

    check_device_spec(device, where="onnx: device")
    return ["CPUExecutionProvider"]


def _open_session(onnxruntime, path: Path, device: str | None):
    """(onnxruntime session, sha256 of the model's bytes and of the external data files its
    tensors name), or one DataError naming the file. The session is loaded from the model's path,
    so external data (``w.data``) is found beside the model, never in the current folder."""
    if not path.is_file():
        raise DataError(f"{path}: ONNX model not found")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read the ONNX model ({exc.strerror or exc})") from exc
    digest = hashlib.sha256(data)
    for location, file in _external_data_files(path, data):
        digest.update(f"\nexternal {location}\n".encode("utf-8", "surrogateescape"))
        try:
            with open(file, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    digest.update(block)
        except OSError as exc:
            raise DataError(f"{path}: cannot read its external data {file} ({exc.strerror or exc})") from exc
    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3  # onnxruntime's warnings are about its graph rewrites, not the user's input
    providers = _providers(device)
    try:
        session = onnxruntime.InferenceSession(str(path), options, providers=providers)
    except Exception as exc:  # onnxruntime raises its own classes (InvalidProtobuf, Fail, ...)
        detail = " ".join(str(exc).split())[:200]
        raise DataError(f"{path}: not an ONNX model onnxruntime can load ({detail})") from exc
    return session, digest.hexdigest()


def _external_data_files(path: Path, data: bytes) -> list[tuple[str, Path]]:
    """(location as written, file) of every external data file the model's tensors name, sorted;
    a location that is absolute or leaves the model's folder is refused (DataError)."""
    try:
        import onnx
        from onnx.external_data_helper import ExternalDataInfo, uses_external_data
    except ImportError as exc:
        raise NotAvailableError(
            "--method onnx needs the optional extra: pip install 'fdnet[onnx]' " "(onnx, onnxruntime)"
        ) from exc
    try:
        model = onnx.load_from_string(data)
    except Exception as exc:  # onnx raises DecodeError and others for what is not a model
        detail = " ".join(str(exc).split())[:200]
        raise DataError(f"{path}: not an ONNX model onnxruntime can load ({detail})") from exc
    folder = path.resolve().parent
    found: dict[str, Path] = {}
    for tensor in _tensors(model.graph):
        if not uses_external_data(tensor):
            continue
        location = ExternalDataInfo(tensor).location
        file = (folder / location).resolve()
        if not location or os.path.isabs(location) or not file.is_relative_to(folder):
            raise DataError(
                f"{path}: a tensor's external data {location!r} is not a file inside the model's "
                f"folder {folder}; such a model is refused"
            )
        if not file.is_file():
            raise DataError(f"{path}: its external data file {file} is missing")
        found[location] = file
    return sorted(found.items())


def _tensors(graph):
    """Every tensor a graph holds: initializers, sparse ones, and node attributes (subgraphs too)."""
    yield from graph.initializer
    for sparse in graph.sparse_initializer:
        yield sparse.values
        yield sparse.indices
    for node in graph.node:
        for attribute in node.attribute:
            if attribute.HasField("t"):
                yield attribute.t
            yield from attribute.tensors
            if attribute.HasField("g"):
                yield from _tensors(attribute.g)
            for sub in attribute.graphs:
                yield from _tensors(sub)


def _input_layout(path: Path, shape: list, layout, where) -> tuple[str | None, list, bool]:
    """(layout, the graph's (H, W) dims, whether the graph fixes the layout) of an image input of
    ``shape``; ``layout`` (given or from metadata, ``where``) settles a graph that does not say
    which axis holds the 3 channels; None where nothing does (the caller warns, then takes
    NCHW). DataError for an input whose channels are fixed and not 3."""
    fixed = [d if isinstance(d, int) and d > 0 else None for d in shape]
    if layout is not None:
        layout = str(layout).lower()
        if layout not in LAYOUT_CHOICES:
            raise ConfigError(f"{path}: layout={layout!r} ({where}); choose {' or '.join(LAYOUT_CHOICES)}")
    first, last = fixed[1] == 3, fixed[3] == 3
    if first != last:  # the graph says
        own = "nchw" if first else "nhwc"
        if layout is not None and layout != own:
            raise ConfigError(
                f"{path}: the graph's input {shape} is {own.upper()}, but layout ({where}) says " f"{layout}"
            )
        return own, (shape[2:4] if first else shape[1:3]), True
    if not first and fixed[1] is not None and fixed[3] is not None:
        raise DataError(
            f"{path}: input of shape {shape} takes neither 3 channels first (N, 3, H, W) nor last "
            "(N, H, W, 3); fdnet gives a model RGB (or BGR) images"
        )
    return layout, (shape[2:4] if layout != "nhwc" else shape[1:3]), False


def _check_scale(mean: np.ndarray, std: np.ndarray, path: Path) -> None:
    """Refuse mean/std on the 0..255 scale: applied to images in [0, 1] they give the model
    values far from any it was trained on, and every vector would be silently wrong."""
    if ((mean < 0) | (mean > 1)).any() or (std > 1).any():
        raise ConfigError(
            f"{path}: mean [{', '.join(f'{v:.6g}' for v in mean)}] and std "
            f"[{', '.join(f'{v:.6g}' for v in std)}] "
            "are not on the [0, 1] scale fdnet's images have (mean within [0, 1], std at most 1); "
            "values on the 0..255 scale are divided by 255 (123.675 -> 0.485)"
        )


@dataclass(frozen=True)
class ONNXSettings(MethodSettings):
    """Preprocessing left unset comes from the model's metadata (``fdnet.KEY`` or ``KEY``)."""

    method: ClassVar[str] = "onnx"
    #: the ONNX model file (--weights MODEL.onnx; required)
    weights: str | None = None
    #: (height, width) the model takes, HxW or [H, W] (default: the graph's or the metadata's)
    input_size: tuple[int, int] | str | None = None
    #: subtracted from the [0, 1] images: a number or one per channel (default 0)
    mean: float | tuple[float, float, float] | str | None = None
    #: the images are divided by it after the mean: a number or one per channel, > 0 (default 1)
    std: float | tuple[float, float, float] | str | None = None
    #: rgb or bgr (default rgb)
    channels: str | None = None
    #: l2 (unit vectors) or none (as the model returns them; default l2)
    normalise: str | None = None
    #: the output holding the vectors (default the first)
    output: str | None = None
    #: nchw or nhwc, for a graph that does not fix where the channels are (default nchw)
    layout: str | None = None
    #: auto, cpu or cuda (onnxruntime's CUDA provider)
    device: str | None = "auto"

    def check(self) -> None:
        self.need_path("weights")
        if self.input_size is not None:
            _parse_size(self.input_size, "onnx: input_size")
        for name in ("mean", "std"):
            if getattr(self, name) is not None:
                _parse_triple(getattr(self, name), f"onnx: {name}")
        if self.std is not None and (_parse_triple(self.std, "onnx: std") <= 0).any():
            raise ConfigError("onnx: std must not be 0 or below")
        self.need_text("channels", CHANNEL_CHOICES, optional=True)
        self.need_text("normalise", NORMALISE_CHOICES, optional=True)
        self.need_text("layout", LAYOUT_CHOICES, optional=True)
        self.need_text("output", optional=True)
        self.need_device()


def _setting(metadata: dict, key: str, given):
    """(value, where it came from): the given setting, else the model's metadata (``fdnet.KEY``
    or ``KEY``), else (None, None)."""
    if given is not None:
        return given, "given"
    for k in (f"fdnet.{key}", key):
        if k in metadata:
            return metadata[k], f"model metadata {k}"
    return None, None


class ONNXDescriptor(Descriptor):
    """An ONNX model's output vectors (module docstring). Settings: :class:`ONNXSettings`."""

    name = "onnx"
    Settings: ClassVar[type] = ONNXSettings

    def __init__(self, settings: ONNXSettings | None = None, **options):
        conf = self.conf = ONNXSettings.build(settings, options)
        if not conf.weights:
            raise ConfigError("onnx: give the model with --weights MODEL.onnx")
        try:
            import onnxruntime
        except ImportError as exc:
            raise NotAvailableError(
                "--method onnx needs the optional extra: pip install 'fdnet[onnx]' " "(onnxruntime)"
            ) from exc
        path = Path(conf.weights)
        self.weights = str(path)
        self.session, self.model_sha256 = _open_session(onnxruntime, path, conf.device)
        self.device = "cuda" if self.session.get_providers()[0] == "CUDAExecutionProvider" else "cpu"
        metadata = self.session.get_modelmeta().custom_metadata_map or {}
        shape, guessed = self._read_input(path, conf, metadata)
        self._read_preprocessing(path, conf, metadata)
        self._read_output(path, conf, metadata)
        logger.debug(
            "onnx model %s: input %s %s, %s, output %s (%d-d), providers %s",
            path,
            self.input_name,
            self.layout,
            self.input_size,
            self.output_name,
            self._dim,
            self.session.get_providers(),
        )
        if guessed:  # said once the model is accepted: a refused one gets its one error line only
            logger.warning(
                f"{path}: the graph's input {shape} does not say which axis holds the channels; fdnet "
                "feeds it (N, 3, H, W): give --method-set layout=nhwc if it takes (N, H, W, 3)"
            )

    def _read_input(self, path: Path, conf: ONNXSettings, metadata: dict) -> tuple[list, bool]:
        """The graph's one image input: its name, layout, batch limit, type and size (given, else
        the model's metadata, else the graph's fixed size); (its shape, whether the layout was guessed)."""
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise DataError(
                f"{path}: the model takes {len(inputs)} inputs ({', '.join(i.name for i in inputs)}); "
                "a descriptor model takes one image batch"
            )
        self.input_name = inputs[0].name
        shape = list(inputs[0].shape)
        if len(shape) != 4:
            raise DataError(
                f"{path}: input {self.input_name} has shape {shape}; expected an image batch " "(N, 3, H, W)"
            )
        given_layout, where = _setting(metadata, "layout", conf.layout)
        self.layout, fixed, self._graph_layout = _input_layout(path, shape, given_layout, where)
        guessed, self.layout = self.layout is None, self.layout or "nchw"
        self.batch_limit = shape[0] if isinstance(shape[0], int) and shape[0] > 0 else None
        self.input_type = inputs[0].type
        if self.input_type not in ("tensor(float)", "tensor(float16)"):
            raise DataError(
                f"{path}: input {self.input_name} is {self.input_type}; fdnet gives a model float "
                "images (float32 or float16)"
            )
        fixed = [d if isinstance(d, int) and d > 0 else None for d in fixed]
        given_size, where = _setting(metadata, "input_size", conf.input_size)
        if given_size is not None:
            size = _parse_size(given_size, f"{path}: input_size ({where})")
            if all(fixed) and tuple(fixed) != size:
                raise ConfigError(
                    f"{path}: the graph's input is {fixed[0]}x{fixed[1]}, but input_size ({where}) "
                    f"says {size[0]}x{size[1]}"
                )
        elif all(fixed):
            size = (int(fixed[0]), int(fixed[1]))
        else:
            raise ConfigError(
                f"{path}: the model's input size is not fixed ({shape}) and neither "
                "--method-set input_size=HxW nor its metadata gives one"
            )
        self.input_size = size
        return shape, guessed

    def _read_preprocessing(self, path: Path, conf: ONNXSettings, metadata: dict) -> None:
        """How images are prepared for the model (mean, std, channel order) and how its vectors
        are normalised: given, else the model's metadata, else the defaults."""
        value, where = _setting(metadata, "mean", conf.mean)
        self.mean = _parse_triple(0.0 if value is None else value, f"{path}: mean ({where or 'default'})")
        value, where = _setting(metadata, "std", conf.std)
        self.std = _parse_triple(1.0 if value is None else value, f"{path}: std ({where or 'default'})")
        if (self.std <= 0).any():
            raise ConfigError(f"{path}: std must not be 0 or below ({where or 'default'})")
        _check_scale(self.mean, self.std, path)
        value, where = _setting(metadata, "channels", conf.channels)
        self.channels = str(value or "rgb").lower()
        if self.channels not in CHANNEL_CHOICES:
            raise ConfigError(f"{path}: channels={value!r} ({where}); choose {' or '.join(CHANNEL_CHOICES)}")
        value, where = _setting(metadata, "normalise", conf.normalise)
        self.normalise = str(value or "l2").lower()
        if self.normalise not in NORMALISE_CHOICES:
            raise ConfigError(f"{path}: normalise={value!r} ({where}); choose {' or '.join(NORMALISE_CHOICES)}")

    def _read_output(self, path: Path, conf: ONNXSettings, metadata: dict) -> None:
        """The output holding the vectors (given, else the metadata's, else the first) and their
        length (from the graph, else from describing one grey image)."""
        outputs = self.session.get_outputs()
        value, where = _setting(metadata, "output", conf.output)
        names = [o.name for o in outputs]
        if value is not None and value not in names:
            raise ConfigError(
                f"{path}: output {value!r} ({where}) is not one of the model's outputs: " f"{', '.join(names)}"
            )
        self.output_name = value or names[0]
        out_shape = next(o.shape for o in outputs if o.name == self.output_name)
        if out_shape is not None and len(out_shape) != 2:
            raise DataError(
                f"{path}: output {self.output_name} has shape {out_shape}; a descriptor model returns " "(N, D) vectors"
            )
        self._dim = out_shape[1] if isinstance(out_shape[1], int) and out_shape[1] > 0 else None
        if self._dim is None:  # not fixed in the graph: one grey image says (as returned, unnormalised)
            normalise, self.normalise = self.normalise, "none"
            try:
                self._dim = int(self.describe(np.full((1, *self.input_size, 3), 0.5, np.float32)).shape[1])
            finally:
                self.normalise = normalise

    @property
    def dim(self) -> int:
        return int(self._dim)

    def settings(self) -> dict:
        return {
            "input_size": list(self.input_size),
            "weights": self.weights,
            "model_sha256": self.model_sha256,
            "mean": [float(v) for v in self.mean],
            "std": [float(v) for v in self.std],
            "channels": self.channels,
            "normalise": self.normalise,
            "output": self.output_name,
            **({} if self._graph_layout else {"layout": self.layout}),
        }

    def fingerprint(self) -> str:
        # The model's bytes are in model_sha256; the session holds no array the base class could hash.
        settings = {k: v for k, v in self.settings().items() if k != "weights"}
        return hashlib.sha256(f"method={self.name}\n{json.dumps(settings, sort_keys=True)}".encode()).hexdigest()

    def _prepare(self, images: np.ndarray) -> np.ndarray:
        x = np.asarray(images, dtype=np.float32)
        if self.channels == "bgr":
            x = x[..., ::-1]
        x = (x - self.mean) / self.std
        if self.layout == "nchw":
            x = x.transpose(0, 3, 1, 2)
        x = np.ascontiguousarray(x)
        return x.astype(np.float16) if self.input_type == "tensor(float16)" else x

    def describe(self, images: np.ndarray) -> np.ndarray:
        images = np.asarray(images)
        step = self.batch_limit or max(1, len(images))
        parts = []
        for start in range(0, len(images), step):
            chunk = self._prepare(images[start : start + step])
            if self.batch_limit and len(chunk) < self.batch_limit:  # a graph fixed at batch B: pad the last chunk
                padding = np.zeros((self.batch_limit - len(chunk), *chunk.shape[1:]), chunk.dtype)
                chunk = np.concatenate([chunk, padding])
            try:
                out = self.session.run([self.output_name], {self.input_name: chunk})[0]
            except Exception as exc:  # onnxruntime's own error classes
                detail = " ".join(str(exc).split())[:200]
                raise DataError(
                    f"{self.weights}: the model failed on a batch of shape {list(chunk.shape)} " f"({detail})"
                ) from exc
            out = np.asarray(out)
            if out.ndim != 2 or out.shape[0] != len(chunk):
                raise DataError(
                    f"{self.weights}: output {self.output_name} has shape {list(out.shape)} for "
                    f"{len(chunk)} images; a descriptor model returns (N, D) vectors"
                )
            dim = getattr(self, "_dim", None)
            if dim is not None and out.shape[1] != dim:
                raise DataError(
                    f"{self.weights}: output {self.output_name} has shape {list(out.shape)} for a batch "
                    f"of {len(chunk)} images but ({dim},) per image for one; a descriptor model's "
                    "vector length must not depend on the batch"
                )
            parts.append(out[: min(step, len(images) - start)].astype(np.float32))
        vectors = np.concatenate(parts) if parts else np.zeros((0, getattr(self, "_dim", 0) or 0), np.float32)
        # no direction: every score against an all-zero vector would be 0, never a match, without a word
        vectors = check_vectors(
            vectors,
            f"{self.weights}: the model's output",
            lambda i: f"image {i} of a batch of {len(vectors)}",
            directions=self.normalise == "l2",
        )
        return l2_normalize(vectors) if self.normalise == "l2" else vectors


def model_metadata(
    input_size: Sequence[int], mean=None, std=None, channels: str = "rgb", normalise: str = "l2"
) -> dict[str, str]:
    """The metadata ``fdnet export`` writes into a model so ``--method onnx`` needs no settings."""
    out = {
        "fdnet.input_size": f"{int(input_size[0])}x{int(input_size[1])}",
        "fdnet.channels": channels,
        "fdnet.normalise": normalise,
    }
    if mean is not None:
        out["fdnet.mean"] = json.dumps([float(v) for v in mean])
    if std is not None:
        out["fdnet.std"] = json.dumps([float(v) for v in std])
    return out
