"""The descriptor interface.

A descriptor turns a batch of images, float32 RGB in [0, 1] with shape (N, H, W, 3) at its own
``input_size``, into float32 vectors (N, D), L2-normalised unless it says otherwise. It also says
how two sets of its vectors are compared: by default the dot product (= cosine similarity for
unit vectors), which lets matching use BLAS and faiss. A method whose comparison is not a dot
product (SeqSLAM's sum of absolute differences, Landmarks' region matching) overrides
:meth:`Descriptor.similarity` and sets ``dot_product_similarity = False``; indexed search then
refuses it instead of silently computing the wrong thing.
"""

from __future__ import annotations

import contextlib
from abc import ABC, abstractmethod
from pathlib import Path
from typing import ClassVar, Sequence

import numpy as np

from fdnet.descriptors.settings import MethodSettings


def l2_normalize(x: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    with np.errstate(over="ignore"):
        norm = np.linalg.norm(x, axis=-1, keepdims=True)
    odd = ~np.isfinite(norm) | (norm < 1e-18)
    norm = np.maximum(norm, eps)
    if odd.any():
        # float32's sum of squares overflows (values near 1e20) or underflows (near 1e-20): take
        # those rows' norms in float64 instead of giving zeros (1e25) or tiny vectors (1e-29)
        exact = np.linalg.norm(x.astype(np.float64), axis=-1, keepdims=True)
        norm[odd] = np.where(exact > 0, exact, eps)[odd].astype(np.float32)
    return x / norm


def row_norms(v: np.ndarray, block_bytes: int = 64 << 20) -> np.ndarray:
    """Every row's L2 norm, taken in float64 (no float32 overflow or underflow) a block of rows
    at a time, so a large matrix never gets a float64 copy of itself."""
    v = np.asarray(v)
    rows = max(1, block_bytes // max(1, 8 * v.shape[1]))
    return (
        np.concatenate([np.linalg.norm(v[i : i + rows].astype(np.float64), axis=1) for i in range(0, len(v), rows)])
        if len(v)
        else np.zeros(0)
    )


def check_vectors(vectors, source, label=None, *, directions: bool = True) -> np.ndarray:
    """The one guard for vectors entering fdnet (a model's output, a vectors file, a database
    add, an extraction): ``vectors`` as (N, D) float32, or a DataError naming ``source`` (a file)
    and the first bad row (``label(i)`` names row i; default "row i"). Refused: a value that is
    NaN, infinite or beyond float32's range, and (``directions``) an all-zero row, which has no
    direction and so could never be matched. Norms are taken in float64, so vectors of tiny
    (1e-29) or huge (1e25) values are neither zero nor overflowing."""
    from fdnet.errors import DataError

    label = label or (lambda i: f"row {i}")
    with np.errstate(over="ignore", invalid="ignore"):
        v = np.asarray(vectors, dtype=np.float32)
    if v.ndim != 2:
        raise DataError(f"{source}: vectors of shape {tuple(v.shape)}; expected (images, length)")
    bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if len(bad):
        raise DataError(
            f"{source}: the vector of {label(int(bad[0]))} holds NaN, infinity or a number beyond "
            f"float32's range ({len(bad)} of {len(v)} vectors); refused"
        )
    if directions and v.size:
        zero = np.flatnonzero(row_norms(v) == 0)
        if len(zero):
            raise DataError(
                f"{source}: the vector of {label(int(zero[0]))} is all zero ({len(zero)} of {len(v)} "
                "vectors): it has no direction and could never be matched; refused"
            )
    return v


#: settings that say where a descriptor's weights were read from, not what they are: left out of
#: :meth:`Descriptor.fingerprint` (the weights' bytes are in it)
LOCATION_SETTINGS = frozenset({"checkpoint", "weights", "vocabulary", "fit", "fitted_on"})


class Descriptor(ABC):
    #: name used by ``--method`` and in reports
    name: ClassVar[str] = "descriptor"
    #: True when ``similarity`` is the dot product of the vectors (indexable with faiss)
    dot_product_similarity: ClassVar[bool] = True
    #: the largest value ``similarity`` can return (1 for the cosine of unit vectors); the
    #: ``ratio`` acceptance rule measures distances as ``ceiling - similarity``
    similarity_ceiling: ClassVar[float] = 1.0
    #: True when ``describe`` also takes uint8 images (0..255, what the streaming pipeline then
    #: loads: a quarter of the bytes, converted on the descriptor's device). The torch
    #: descriptors do; float32 in [0, 1] is always accepted.
    accepts_uint8: ClassVar[bool] = False
    #: True when ``describe`` reads vectors computed elsewhere, by each image's path: callers
    #: describe a batch inside :meth:`images_of` its paths (the pixels are not needed)
    keyed_by_image: ClassVar[bool] = False
    #: True when the method also describes each image's appearance (FDNet's appearance encoder):
    #: :meth:`describe_appearance` and :meth:`describe_both` work
    describes_appearance: ClassVar[bool] = False
    #: the torch device a method runs on (None: numpy and OpenCV methods, on the CPU)
    device = None
    #: the run directory a trained method's weights (or a trunk's block) come from; None for
    #: untrained methods (held-out checks and calibrations stored in runs read it)
    run_dir = None

    #: (height, width) images are resized to before ``describe``
    input_size: tuple[int, int]

    #: the method's settings dataclass (:mod:`fdnet.descriptors.settings`): its fields are the
    #: settings ``create`` and the command line accept; the constructor takes an instance of it
    #: and keyword overrides of its fields
    Settings: ClassVar[type[MethodSettings]] = MethodSettings
    #: the settings this descriptor was built with (an instance of :attr:`Settings`)
    conf: MethodSettings | None = None

    @property
    @abstractmethod
    def dim(self) -> int:
        """Length of one vector."""

    @abstractmethod
    def describe(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) float32 in [0, 1] at ``input_size`` -> (N, dim) float32."""

    def settings(self) -> dict:
        """The settings that define this descriptor (reported next to results)."""
        return {"input_size": list(self.input_size)}

    def describe_appearance(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) -> (N, L) appearance vectors, for a method that :attr:`describes_appearance`."""
        raise NotImplementedError(f"{self.name} describes no appearance")

    def describe_both(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(place vectors, appearance vectors) of the same images, for a method that
        :attr:`describes_appearance`."""
        raise NotImplementedError(f"{self.name} describes no appearance")

    def fit(self, images_or_paths: Sequence[Path] | np.ndarray) -> None:  # noqa: B027 - optional hook
        """Learn from training/reference images, for methods that need to (e.g. a DBoW
        vocabulary). Default: nothing to learn."""

    @contextlib.contextmanager
    def images_of(self, paths: Sequence):
        """Within the block, the images ``describe`` gets are those of ``paths``, in order: a
        method :attr:`keyed_by_image` reads their vectors by path; the others do not need them."""
        yield self

    @property
    def needs_fit(self) -> bool:
        """True when ``describe`` cannot run before ``fit``."""
        return False

    @property
    def min_fit_images(self) -> int:
        """The fewest images ``fit`` can learn from (e.g. L + 1 for an L-dimensional whitening);
        callers that fit on reference images they did not choose check it first."""
        return 1

    def similarity(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        """(Q, D), (R, D) -> (Q, R) float32, higher = more similar."""
        return np.asarray(queries, dtype=np.float32) @ np.asarray(references, dtype=np.float32).T

    def fingerprint(self) -> str:
        """sha256 hex of what makes this descriptor's vectors what they are: its name, its
        settings, and the bytes of every weight it holds (the state_dict of each torch module and
        every numpy array among its attributes, and one level inside fdnet helper objects such as
        a backbone trunk or a vocabulary). Two run directories with different weights differ;
        reloading the same one gives the same fingerprint. A place database stores it so vectors
        from another model are refused rather than silently mixed."""
        import hashlib
        import json

        digest = hashlib.sha256()
        digest.update(f"method={self.name}\n".encode())
        # Where the weights were read from is no part of them: the same run directory named as
        # "run", "./run" or an absolute path (a database records absolute paths) must match.
        settings = {k: v for k, v in self.settings().items() if k not in LOCATION_SETTINGS}
        digest.update(json.dumps(settings, sort_keys=True, default=str).encode())
        for label, data in _weight_bytes(self, "self", depth=1, seen=set()):
            digest.update(f"\n{label}\n".encode())
            digest.update(data)
        return digest.hexdigest()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.settings()})"


def _weight_bytes(value, label: str, depth: int, seen: set):
    """Yield (label, bytes) for every weight tensor or array reachable from ``value``, in an
    order that depends only on attribute names (so the fingerprint is deterministic). Labels
    carry dtype and shape: the same bytes reinterpreted are different weights."""
    import sys

    if id(value) in seen:
        return
    torch = sys.modules.get("torch")  # no torch loaded means no torch module can be held
    if isinstance(value, np.ndarray):
        if not value.dtype.hasobject:  # object arrays hold pointers, not weights
            seen.add(id(value))
            yield f"{label}:{value.dtype.str}{list(value.shape)}", np.ascontiguousarray(value).tobytes()
        return
    if torch is not None and isinstance(value, (torch.nn.Module, torch.Tensor)):
        seen.add(id(value))
        tensors = value.state_dict() if isinstance(value, torch.nn.Module) else {"": value}
        for key in sorted(tensors):
            t = tensors[key].detach().cpu().contiguous()
            # Viewed as bytes: numpy has no bfloat16, and this keeps the exact stored bits.
            data = t.reshape(-1).view(torch.uint8).numpy().tobytes()
            yield f"{label}.{key}:{t.dtype}{list(t.shape)}", data
        return
    if isinstance(value, dict):
        seen.add(id(value))
        for key in sorted(value, key=str):
            yield from _weight_bytes(value[key], f"{label}[{key!s}]", depth, seen)
        return
    if isinstance(value, (list, tuple)):
        seen.add(id(value))
        for i, item in enumerate(value):
            yield from _weight_bytes(item, f"{label}[{i}]", depth, seen)
        return
    attributes = getattr(value, "__dict__", None)
    if attributes is None or depth < 0:
        return
    if label != "self" and not type(value).__module__.startswith("fdnet."):
        return  # only our own helper objects: walking arbitrary library objects is unbounded
    seen.add(id(value))
    for key in sorted(attributes):
        yield from _weight_bytes(attributes[key], f"{label}.{key}", depth - 1, seen)


def describe_paths(
    descriptor: Descriptor,
    paths: Sequence[str | Path],
    batch_size: int = 64,
    progress: bool = False,
    timing: dict | None = None,
    workers: int | None = None,
) -> np.ndarray:
    """Describe ``paths`` at the descriptor's input size, streaming them through
    :func:`fdnet.descriptors.pipeline.describe_stream` (decoding in worker processes overlapped
    with the model, a few batches in memory at a time) into one (N, dim) float32 array.

    When ``timing`` is a dict it receives ``seconds_describe`` (model time only, excluding image
    decoding) and ``num_images``, for ms/image reports. ``workers``: decoding processes (None =
    one per spare core; 0 = decode in this process).
    """
    from fdnet.descriptors.pipeline import PipelineSettings, describe_stream

    paths = list(paths)
    out = None
    for start, vectors in describe_stream(
        descriptor, paths, PipelineSettings(batch_size, workers, progress), timing=timing
    ):
        vectors = np.asarray(vectors, dtype=np.float32)
        if out is None:
            out = np.empty((len(paths), vectors.shape[1]), dtype=np.float32)
        out[start : start + len(vectors)] = vectors
    if out is None:
        if timing is not None:
            timing.setdefault("seconds_describe", 0.0)
            timing.setdefault("num_images", 0)
        return np.zeros((0, descriptor.dim), dtype=np.float32)
    return out
