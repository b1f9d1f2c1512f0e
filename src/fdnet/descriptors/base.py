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

import time
from abc import ABC, abstractmethod
from pathlib import Path
from typing import ClassVar, Sequence

import numpy as np

from fdnet.data.images import load_images


def l2_normalize(x: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    norm = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.maximum(norm, eps)


class Descriptor(ABC):
    #: name used by ``--method`` and in reports
    name: ClassVar[str] = "descriptor"
    #: True when ``similarity`` is the dot product of the vectors (indexable with faiss)
    dot_product_similarity: ClassVar[bool] = True

    #: (height, width) images are resized to before ``describe``
    input_size: tuple[int, int]

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

    def fit(self, images_or_paths: Sequence[Path] | np.ndarray) -> None:  # noqa: B027 - optional hook
        """Learn from training/reference images, for methods that need to (e.g. a DBoW
        vocabulary). Default: nothing to learn."""

    @property
    def needs_fit(self) -> bool:
        """True when ``describe`` cannot run before ``fit``."""
        return False

    def similarity(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        """(Q, D), (R, D) -> (Q, R) float32, higher = more similar."""
        return np.asarray(queries, dtype=np.float32) @ np.asarray(references, dtype=np.float32).T

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.settings()})"


def describe_paths(
    descriptor: Descriptor,
    paths: Sequence[str | Path],
    batch_size: int = 64,
    progress: bool = False,
    timing: dict | None = None,
) -> np.ndarray:
    """Load ``paths`` at the descriptor's input size in batches and describe them.

    When ``timing`` is a dict it receives ``seconds_describe`` (model time only, excluding image
    decoding) and ``num_images``, for ms/image reports.
    """
    paths = list(paths)
    chunks = []
    spent = 0.0
    iterator = range(0, len(paths), batch_size)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc=f"describe [{descriptor.name}]", unit="batch", leave=False)
    for start in iterator:
        images = load_images(paths[start:start + batch_size], descriptor.input_size)
        t0 = time.perf_counter()
        chunks.append(np.asarray(descriptor.describe(images), dtype=np.float32))
        spent += time.perf_counter() - t0
    if timing is not None:
        timing["seconds_describe"] = spent
        timing["num_images"] = len(paths)
    if not chunks:
        return np.zeros((0, descriptor.dim), dtype=np.float32)
    return np.concatenate(chunks, axis=0)
