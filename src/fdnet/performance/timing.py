"""How fast: the timing kernels of ``fdnet benchmark`` and of reproduce's runtime experiment.

Extraction ms/image and matching ms/query, with references measured in the same run (the
paper's Table 2/5 GPU figures, :mod:`fdnet.paper`, are quoted; this machine's own fp32
and bf16 GEMM speeds and fp32-eager FDNet are measured) so every figure comes with a ratio.
Timings are medians over repeats after a warm-up; nothing here is asserted in tests (machines
are shared and noisy), the command prints what it measured.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from fdnet.backbones import CachePasses, autocast, resolve_device, synchronize


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (or what platform says where there is none)."""
    import platform

    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass  # not Linux: platform's name stands
    return platform.processor() or platform.machine()


def median_seconds(fn: Callable[[], object], repeats: int = 5, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def gemm_gflops(size: int = 1024, repeats: int = 5, dtype: str = "fp32", device=None) -> float:
    """This machine's matrix-multiply speed (torch, ``size``^3, fp32 or bf16) on ``device``
    (default the CPU): the reference every extraction figure is compared with."""
    import torch

    device = torch.device("cpu" if device is None else device)
    kind = {"fp32": torch.float32, "bf16": torch.bfloat16}[dtype]
    a = torch.randn(size, size, device=device).to(kind)
    b = torch.randn(size, size, device=device).to(kind)

    def run():
        out = a @ b
        synchronize(device)
        return out

    seconds = median_seconds(run, repeats=repeats, warmup=2)
    return 2 * size**3 / seconds / 1e9


def gemv_ms(vectors: np.ndarray, repeats: int = 5) -> float:
    """Median ms of one (places x dim) @ (dim,) product on one thread: the reference for the
    exhaustive search, which reads every vector once per frame."""
    from threadpoolctl import threadpool_limits

    v = vectors[0].copy()
    times = []
    with threadpool_limits(1, user_api="blas"):
        for _ in range(repeats):
            t0 = time.perf_counter()
            vectors @ v
            times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times)) if times else math.nan


def content_flops(config) -> int:
    """Floating-point operations (multiply and add counted separately) of ``FDNet.content`` for
    one image of an FDNet model config, counted by ``torch.utils.flop_counter`` (convolutions
    and matrix products; normalisation and activations are not counted)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from fdnet.methods.fdnet.model import FDNet

    model = FDNet(config).eval()
    x = torch.rand(1, 3, *config.input_size)
    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        model.content(x)
    return int(counter.get_total_flops())


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

    from fdnet.methods.fdnet.config import preset
    from fdnet.methods.fdnet.model import FDNet

    config = dataclasses.replace(preset("paper").model, vector_length=vector_length)
    model = FDNet(config).eval()
    input_size = config.input_size
    encoder = model.content_encoder
    out = {}
    for b in (batch, 1):
        x = torch.rand(b, 3, *input_size)
        with torch.inference_mode():
            fp32 = median_seconds(lambda: model.content(x), repeats=repeats)
            # Module.to converts the weights in place (and returns the same module): model.content now runs
            # the channels_last encoder, restored below
            encoder.to(memory_format=torch.channels_last)
            x_cl = x.contiguous(memory_format=torch.channels_last)

            def bf16():
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    return model.content(x_cl)

            fast = median_seconds(bf16, repeats=repeats)
            encoder.to(memory_format=torch.contiguous_format)
        out[f"fp32_batch{b}"] = fp32 / b * 1e3
        out[f"bf16_batch{b}"] = fast / b * 1e3
    return out


def temporary_fdnet_run(folder, preset_name: str = "cpu", vector_length: int | None = None, seed: int = 0):
    """A run directory in ``folder`` holding an FDNet of preset ``preset_name`` with random
    weights (what it costs to run does not depend on them), so timings go through the public
    API (:class:`~fdnet.methods.fdnet.descriptor.FDNetDescriptor`) exactly as a user's run does."""
    import dataclasses
    from pathlib import Path

    import torch

    from fdnet.methods.fdnet.config import preset
    from fdnet.methods.fdnet.model import FDNet
    from fdnet.runs import save_checkpoint

    config = preset(preset_name)
    if vector_length:
        config = dataclasses.replace(config, model=dataclasses.replace(config.model, vector_length=vector_length))
    torch.manual_seed(seed)
    run = Path(folder) / f"{preset_name}-{config.model.vector_length}"
    save_checkpoint(run, FDNet(config.model).named_parts(), config, state={"step": 0})
    return run, config


#: seconds each descriptor path runs before it is timed
WARMUP_SECONDS = 1.0


def descriptor_paths(
    run_dir, images_u8: np.ndarray, repeats: int = 3, device="cpu", compiled: bool = False
) -> dict[str, float]:
    """ms/image of FDNet's descriptor (the public API) on preloaded images: ``fp32_eager`` is
    the float32 path (float32 images, no autocast: what ``describe`` did before devices);
    ``fp32`` what every command runs by default (uint8 images, float32), all images in one call
    as ``fdnet loop-closure`` describes a batch (in forward passes of ``fp32_images_per_pass``
    images: :class:`fdnet.backbones.CachePasses`; ``fp32_one_pass`` the same call in one forward
    pass, as before passes were sized), and ``fp32_one`` one image a call (a robot node's
    ``process``); ``extract`` what ``fdnet extract --bf16`` runs (uint8 images, bf16
    autocast and channels_last where the device runs bf16 natively) and ``extract_one`` the same
    one image a call; with ``compiled``, ``extract_compiled`` is ``fdnet extract --bf16
    --compile`` (and ``compile_seconds`` what compiling took)."""
    from fdnet.methods.fdnet.descriptor import FDNetDescriptor

    out = {}
    count = len(images_u8)
    fp32 = FDNetDescriptor(checkpoint=run_dir, device=device, bf16=False)
    as_float = images_u8.astype(np.float32) / np.float32(255.0)
    out["fp32_eager"] = _settled_median_seconds(lambda: fp32.describe(as_float), repeats=repeats) / count * 1e3
    out["fp32"] = _settled_median_seconds(lambda: fp32.describe(images_u8), repeats=repeats) / count * 1e3
    out["fp32_one"] = _one_at_a_time_ms(fp32, images_u8, repeats)
    out["fp32_images_per_pass"] = _images_per_pass(fp32, images_u8)
    whole = FDNetDescriptor(checkpoint=run_dir, device=device, bf16=False)
    whole._passes = CachePasses(cache_bytes=1 << 62)  # every call's images in one forward pass
    out["fp32_one_pass"] = _settled_median_seconds(lambda: whole.describe(images_u8), repeats=repeats) / count * 1e3
    fast = FDNetDescriptor(checkpoint=run_dir, device=device, bf16=None)
    out["extract"] = _settled_median_seconds(lambda: fast.describe(images_u8), repeats=repeats) / count * 1e3
    out["extract_one"] = _one_at_a_time_ms(fast, images_u8, repeats)
    out["extract_bf16"] = bool(fast.bf16)
    if compiled:
        t0 = time.perf_counter()
        comp = FDNetDescriptor(checkpoint=run_dir, device=device, bf16=None, compile=True, batch_size=count)
        comp.describe(images_u8)
        out["compile_seconds"] = time.perf_counter() - t0
        compiled_seconds = _settled_median_seconds(lambda: comp.describe(images_u8), repeats=repeats)
        out["extract_compiled"] = compiled_seconds / count * 1e3
    return out


def _images_per_pass(descriptor, images_u8: np.ndarray) -> int:
    """The images a CPU forward pass of the fp32 ``descriptor`` holds (measured as it measures)."""
    import torch

    from fdnet.backbones import images_to_device

    with torch.inference_mode():
        x = images_to_device(images_u8[:1], "cpu", channels_last=True)
        return CachePasses().images_per_pass(descriptor.model, descriptor.model.content, x)


def _one_at_a_time_ms(descriptor, images: np.ndarray, repeats: int) -> float:
    """ms/image of ``descriptor`` given one image a call (the median of ``repeats`` runs over all
    ``images``, per image)."""

    def each():
        for i in range(len(images)):
            descriptor.describe(images[i : i + 1])

    return _settled_median_seconds(each, repeats=repeats) / len(images) * 1e3


def _settled_median_seconds(fn: Callable[[], object], repeats: int) -> float:
    """:func:`median_seconds` after ``fn`` has run for :data:`WARMUP_SECONDS`: with one warm-up
    call, some paths timed 1.5-2x slower than the same calls later in the same process."""
    start = time.perf_counter()
    while time.perf_counter() - start < WARMUP_SECONDS:
        fn()
    return median_seconds(fn, repeats=repeats, warmup=0)


def gpu_figures(device, run_dir, batch_sizes=(64, 256, 1024), seconds: float = 3.0) -> dict:
    """Images/s of FDNet's descriptor on a GPU ``device``: through the public API
    (``describe`` of uint8 numpy images on the host: transfer, conversion, model, normalisation
    and the copy back) and forward-only (``FDNet.content`` on images already on the device),
    in fp32 and bf16, per batch size. Each figure runs for about ``seconds``."""
    import torch

    from fdnet.methods.fdnet.descriptor import FDNetDescriptor

    device = resolve_device(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else str(device)
    out: dict = {"device": str(device), "name": name}
    for bf16 in (False, True):
        d = FDNetDescriptor(checkpoint=run_dir, device=device, bf16=bf16, batch_size=max(batch_sizes))
        h, w = d.input_size
        for b in batch_sizes:
            host = np.random.default_rng(0).integers(0, 256, size=(b, h, w, 3), dtype=np.uint8)
            on_device = torch.rand(b, 3, h, w, device=device).contiguous(memory_format=torch.channels_last)
            label = f"{'bf16' if bf16 else 'fp32'}_batch{b}"

            def api():
                d.describe(host)

            def forward():
                with torch.inference_mode(), autocast(device, bf16):
                    d.model.content(on_device)
                synchronize(device)

            for name, fn in (("api", api), ("forward", forward)):
                fn()
                synchronize(device)
                count, t0 = 0, time.perf_counter()
                while time.perf_counter() - t0 < seconds:
                    fn()
                    count += 1
                synchronize(device)
                out[f"{name}_{label}_images_per_s"] = count * b / (time.perf_counter() - t0)
    return out


def matching_per_query(num_references: int, dim: int, num_queries: int = 200, seed: int = 0) -> dict[str, float]:
    """ms/query to find the best reference among ``num_references`` unit vectors: numpy exact
    one query at a time (latency), numpy exact batched, faiss flat (exact), faiss HNSW."""
    from fdnet.matching.index import IndexSettings, VectorIndex
    from fdnet.matching.similarity import top_k

    rng = np.random.default_rng(seed)
    refs = rng.normal(size=(num_references, dim)).astype(np.float32)
    refs /= np.linalg.norm(refs, axis=1, keepdims=True)
    queries = refs[rng.integers(0, num_references, num_queries)] + 0.05 * rng.normal(size=(num_queries, dim)).astype(
        np.float32
    )

    def one_at_a_time():
        for q in queries[:50]:
            int(np.argmax(refs @ q))

    out = {
        "numpy_single": median_seconds(one_at_a_time, repeats=3) / 50 * 1e3,
        "numpy_batched": median_seconds(lambda: top_k(queries, refs, 1), repeats=3) / num_queries * 1e3,
    }
    for kind in ("flat", "hnsw"):
        index = VectorIndex(dim, IndexSettings(kind=kind))
        index.add(refs)
        out[f"faiss_{kind}"] = median_seconds(lambda: index.search(queries, 1), repeats=3) / num_queries * 1e3
    return out


def descriptor_extraction(descriptor, images: np.ndarray, repeats: int = 3) -> float:
    """ms/image of ``descriptor.describe`` on preloaded images (decoding excluded)."""
    return median_seconds(lambda: descriptor.describe(images), repeats=repeats) / len(images) * 1e3


# ---------------------------------------------------------------------------- maps at scale
def process_memory() -> dict:
    """This process's memory now, bytes (Linux ``/proc/self/status``): ``VmRSS`` resident,
    ``RssAnon`` of it not backed by a file, ``RssFile`` file pages mapped, ``VmHWM`` the peak
    resident so far. Empty where the file is not (not Linux)."""
    fields = {}
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                key, _, value = line.partition(":")
                if key in ("VmRSS", "RssAnon", "RssFile", "VmHWM"):
                    fields[key] = int(value.split()[0]) * 1024
    except OSError:
        pass
    return fields


def release_free_heap() -> None:
    """Hand the allocator's free heap back to the system (glibc's ``malloc_trim``; nothing where
    there is none), after collecting garbage: what a process measures after it is what it holds,
    not what an earlier step (a map's build) freed and the allocator kept."""
    import ctypes
    import gc

    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def random_map_chunks(size: int, dim: int, seed: int = 0, chunk: int = 100_000):
    """:func:`random_map`'s vectors, ``chunk`` rows at a time (a map too large to hold)."""
    rng = np.random.default_rng(seed)
    for start in range(0, size, chunk):
        block = rng.standard_normal((min(chunk, size - start), dim), dtype=np.float32)
        block /= np.linalg.norm(block, axis=1, keepdims=True)
        yield block


def random_map(size: int, dim: int, seed: int = 0, chunk: int = 100_000) -> np.ndarray:
    """``size`` random unit vectors of length ``dim`` (float32), made in chunks."""
    out = np.empty((size, dim), dtype=np.float32)
    start = 0
    for block in random_map_chunks(size, dim, seed, chunk):
        out[start : start + len(block)] = block
        start += len(block)
    return out


def revisit_queries(map_vectors: np.ndarray, count: int, noise: float = 0.5, seed: int = 1) -> np.ndarray:
    """Queries made from map vectors plus noise (a revisited place lies near its stored
    vector): stored vector + Gaussian noise of expected norm ``noise``, re-normalised. At 0.5 the
    query's cosine to its place is about 0.9."""
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(map_vectors), size=min(count, len(map_vectors)), replace=False)
    dim = map_vectors.shape[1]
    q = map_vectors[pick] + (noise / np.sqrt(dim)) * rng.standard_normal((len(pick), dim), dtype=np.float32)
    return (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)


#: search-time setting -> the index kinds it applies to (for ``scale_rows``'s ``sweep``)
SWEEPABLE = {"ivf_probe": ("ivf", "ivfpq"), "hnsw_ef_search": ("hnsw",)}


def scale_rows(
    map_vectors: np.ndarray,
    queries: np.ndarray,
    kinds,
    settings: dict | None = None,
    source: str = "random",
    single: int = 100,
    log=None,
    sweep: dict | None = None,
) -> list[dict]:
    """Per index kind: build time, memory, ms/query (all queries in one batch: ``ms_per_query``;
    and one at a time over up to ``single`` of them: ``ms_per_query_single``) and recall@1
    against exact search (faiss flat, computed first). ``settings``: kind -> IndexSettings
    overrides. ``sweep``: search-time setting -> values (``ivf_probe`` for ivf/ivfpq,
    ``hnsw_ef_search`` for hnsw): each built index is then measured once per value, without
    rebuilding, one row each."""
    import faiss

    from fdnet.matching.index import IndexSettings, VectorIndex

    say = log or (lambda message: None)
    size, dim = map_vectors.shape
    t0 = time.perf_counter()
    exact = faiss.IndexFlatIP(dim)
    exact.add(map_vectors)
    truth = exact.search(queries, 1)[1][:, 0]
    say(f"  exact top-1 of {len(queries)} queries over {size:,} places: {time.perf_counter() - t0:.1f} s")
    del exact
    rows = []
    for kind in kinds:
        options = dict((settings or {}).get(kind, {}))
        index = VectorIndex(dim, IndexSettings(kind=kind, **options))
        t0 = time.perf_counter()
        for start in range(0, size, 100_000):
            index.add(map_vectors[start : start + 100_000])
        index.build()
        build_s = time.perf_counter() - t0
        memory_mb = index.memory_bytes() / 2**20
        variants = [{}]
        for key, values in (sweep or {}).items():
            if kind in SWEEPABLE.get(key, ()):
                variants = [{key: int(v)} for v in values]
        for variant in variants:
            if variant:
                index.set_search(**variant)
            index.search(queries[:10], 1)  # warm-up
            t0 = time.perf_counter()
            found = index.search(queries, 1)[0][:, 0]
            batched = (time.perf_counter() - t0) / len(queries) * 1e3
            # one query at a time: up to ``single`` queries, or as many as fit in ~5 s (at least 5)
            done, t0 = 0, time.perf_counter()
            for q in queries[:single]:
                index.search(q[None], 1)
                done += 1
                if done >= 5 and time.perf_counter() - t0 > 5.0:
                    break
            one = (time.perf_counter() - t0) / max(done, 1) * 1e3
            row = {
                "map_size": int(size),
                "index": kind,
                "dim": int(dim),
                "build_s": build_s,
                "memory_mb": memory_mb,
                "ms_per_query": batched,
                "ms_per_query_single": one,
                "recall_at_1": float((found == truth).mean()),
                "queries": int(len(queries)),
                "source": source,
                "search": variant,
                "settings": index.describe(),
            }
            label = " ".join(f"{k}={v}" for k, v in variant.items())
            say(
                f"  {kind:6s} {label:17s} build {build_s:7.1f} s  memory {memory_mb:9.1f} MB  "
                f"{batched:8.4f} ms/query batched  {one:8.3f} single  recall@1 {row['recall_at_1']:.3f}"
            )
            rows.append(row)
        del index
    return rows
