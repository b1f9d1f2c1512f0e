"""Where models run, and how fast: devices, images on the device, and the runtime benchmark.

Devices (every command that runs a model, ``--device auto|cpu|cuda|cuda:N``):
:func:`resolve_device` turns the setting into a ``torch.device`` (``auto`` takes the first GPU
when there is one), :func:`images_to_device` sends a batch of images to it as uint8 (a quarter
of float32's bytes) and converts and normalises them there, :func:`autocast` is bfloat16
autocast on that device, and :func:`bf16_native` says whether the device runs bfloat16 natively.
Nothing here names "cuda" as a default: every path takes a ``torch.device``.

Benchmark: extraction ms/image and matching ms/query, with references measured in the same run
(the paper's Table 2/5 GPU figures are quoted, this machine's own fp32 and bf16 GEMM speeds and
fp32-eager FDNet are measured) so every figure comes with a ratio. Used by ``fdnet benchmark``.
Timings are medians over repeats after a warm-up; nothing here is asserted in tests (machines
are shared and noisy), the command prints what it measured.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

# The device primitives live in the leaf module fdnet.backbones (it may import nothing of fdnet
# but fdnet.errors); they are re-exported here, where the rest of the runtime is.
from fdnet.backbones import (  # noqa: F401
    DeviceCopies,
    autocast,
    bf16_native,
    check_device_spec,
    images_to_device,
    resolve_device,
    synchronize,
)

#: Qin et al., Table 2 (TITAN X): FDNet_L extraction ms/image and matching ms/query on Nordland.
PAPER_TABLE2 = {256: (20.9, 0.32), 512: (21.2, 0.35), 1024: (22.6, 0.36), 2048: (28.7, 0.40)}
#: Qin et al., Table 5 (Nordland, 2000 images; extraction on a TITAN X, matching on a Xeon at
#: 2.1 GHz): method -> (extraction ms/image, matching ms/query). Keys are fdnet's method names
#: where fdnet has the method (Conv4 fine-tuned is HybridNet's conv4, DBoW3 is dbow).
PAPER_TABLE5 = {
    "conv3": (136.0, 0.34),
    "gist": (223.0, 0.38),
    "dbow": (2.3, 0.013),
    "landmarks": (737.0, 19.0),
    "hybridnet": (158.0, 0.36),
    "netvlad": (980.0, 0.038),
    "calc": (39.0, 0.31),
    "fdnet": (21.2, 0.35),
}

DEVICE_HELP = ("where models run: auto (a GPU when there is one, else the CPU; default), cpu, cuda or "
               "cuda:N")

def median_seconds(fn: Callable[[], object], repeats: int = 5, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def gemm_gflops(size: int = 1024, repeats: int = 5) -> float:
    """This machine's fp32 matrix-multiply speed (torch), a reference for comparing machines."""
    import torch

    a = torch.randn(size, size)
    b = torch.randn(size, size)
    seconds = median_seconds(lambda: a @ b, repeats=repeats, warmup=2)
    return 2 * size**3 / seconds / 1e9


@dataclass
class Row:
    what: str
    value_ms: float
    unit: str
    reference: str = ""
    ratio: float | None = None  # reference / value: > 1 means faster than the reference
    extra: dict = field(default_factory=dict)


def fdnet_extraction(vector_length=512, batch: int = 32, repeats: int = 5) -> dict[str, float]:
    """ms/image of FDNet's content encoder (the whole descriptor path) at the ``paper`` preset's
    architecture (224x224) in fp32 eager and bf16 autocast + channels_last, at batch ``batch``
    and at batch 1 (latency)."""
    import dataclasses

    import torch

    from fdnet.methods.fdnet.model import FDNet
    from fdnet.methods.fdnet.config import preset

    config = dataclasses.replace(preset("paper").model, vector_length=vector_length)
    model = FDNet(config).eval()
    input_size = config.input_size
    encoder = model.content_encoder
    out = {}
    for b in (batch, 1):
        x = torch.rand(b, 3, *input_size)
        with torch.inference_mode():
            fp32 = median_seconds(lambda: model.content(x), repeats=repeats)
            encoder_cl = encoder.to(memory_format=torch.channels_last)
            x_cl = x.contiguous(memory_format=torch.channels_last)

            def bf16():
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    return model.content(x_cl)

            fast = median_seconds(bf16, repeats=repeats)
            encoder.to(memory_format=torch.contiguous_format)
        out[f"fp32_batch{b}"] = fp32 / b * 1e3
        out[f"bf16_batch{b}"] = fast / b * 1e3
    return out


def matching_per_query(num_references: int, dim: int, num_queries: int = 200,
                       seed: int = 0) -> dict[str, float]:
    """ms/query to find the best reference among ``num_references`` unit vectors: numpy exact
    one query at a time (latency), numpy exact batched, faiss flat (exact), faiss HNSW."""
    from fdnet.matching.index import IndexSettings, VectorIndex
    from fdnet.matching.similarity import top_k

    rng = np.random.default_rng(seed)
    refs = rng.normal(size=(num_references, dim)).astype(np.float32)
    refs /= np.linalg.norm(refs, axis=1, keepdims=True)
    queries = refs[rng.integers(0, num_references, num_queries)] + 0.05 * rng.normal(
        size=(num_queries, dim)).astype(np.float32)

    def one_at_a_time():
        for q in queries[:50]:
            int(np.argmax(refs @ q))

    out = {"numpy_single": median_seconds(one_at_a_time, repeats=3) / 50 * 1e3,
           "numpy_batched": median_seconds(lambda: top_k(queries, refs, 1), repeats=3) / num_queries * 1e3}
    for kind in ("flat", "hnsw"):
        index = VectorIndex(dim, IndexSettings(kind=kind))
        index.add(refs)
        out[f"faiss_{kind}"] = median_seconds(lambda: index.search(queries, 1), repeats=3) / num_queries * 1e3
    return out


def descriptor_extraction(descriptor, images: np.ndarray, repeats: int = 3) -> float:
    """ms/image of ``descriptor.describe`` on preloaded images (decoding excluded)."""
    return median_seconds(lambda: descriptor.describe(images), repeats=repeats) / len(images) * 1e3
