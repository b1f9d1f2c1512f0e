"""The figures of ``fdnet benchmark``: extraction ms/image and matching ms/query on this machine,
each stated against references measured in the same run (fp32 and bf16 GEMM rates, FDNet's fp32
eager path) and against the paper's Table 2/5 (TITAN X); GPU figures when a GPU is present; and
indexed search on maps of 10^3-10^6 places. Nothing here is asserted by tests: machines are
shared and noisy, so the report holds ratios measured side by side.

:func:`fdnet.performance.benchmark_plan.plan_benchmark` checks the settings (every refusal before
the first measurement); :func:`run_benchmark` measures and writes the tables through an ``out``
callable (the command passes ``print``: the tables are its output) and returns every figure as a
dict.
"""

from __future__ import annotations

import contextlib
import dataclasses
import platform
import tempfile
from typing import Callable

import numpy as np

from fdnet.errors import ConfigError
from fdnet.performance.benchmark_plan import BenchmarkPlan


def _images(plan: BenchmarkPlan, size, uint8: bool = False):
    import numpy as np

    from fdnet.data.images import list_images, load_image_uint8, load_images

    if plan.images:
        paths = list_images(plan.images)[: plan.num_images]
        if uint8:
            return np.stack([load_image_uint8(p, size) for p in paths])
        return load_images(paths, size)
    from fdnet.data.synthetic import render_route

    frames = render_route(frames=plan.num_images, conditions=("summer",), seed=0, size=tuple(size))
    images = np.asarray(frames["summer"], dtype=np.float32)
    if uint8:
        return np.clip(np.rint(images * 255.0), 0, 255).astype(np.uint8)
    return images


def _read_vectors(path: str, what: str):
    from pathlib import Path

    import numpy as np

    from fdnet.errors import DataError

    p = Path(path)
    if not p.is_file():
        raise DataError(f"{p}: {what} file not found")
    try:
        if p.suffix == ".npz":
            with np.load(p, allow_pickle=False) as z:
                key = "content" if "content" in z.files else (z.files[0] if len(z.files) == 1 else None)
                if key is None:
                    raise DataError(f"{p}: an .npz without a 'content' array (has {', '.join(z.files)})")
                v = z[key]
        else:
            from fdnet.data.arrays import load_npy

            v = load_npy(p, ndim=2, what=what)
    except (ValueError, OSError) as exc:
        raise DataError(f"{p}: cannot read {what} ({exc})") from exc
    v = np.asarray(v, dtype=np.float32)
    if v.ndim != 2 or len(v) == 0 or not np.isfinite(v).all():
        raise DataError(f"{p}: {what} must be a finite (N, D) array with N > 0, got shape {v.shape}")
    return np.ascontiguousarray(v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12))


@contextlib.contextmanager
def _terminate_unwinds():
    """SIGTERM (``kill``, a scheduler) ends the run as Ctrl-C does, so the scratch folder is
    removed on the way out: it holds the loop part's maps, tens of GB at 10^7 places."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a repeated SIGTERM must not cut the clean-up short
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        # (None: a handler set outside Python, which cannot be put back; the default stands in)
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def run_benchmark(plan: BenchmarkPlan, out: Callable[[str], None], json_path: str | None = None) -> dict:
    """Measure the parts of ``plan``, writing each table's lines to ``out``; returns every figure
    (and writes them to ``json_path`` as JSON, atomically, when given: checked writable first)."""
    import torch

    from fdnet.backbones import resolve_device
    from fdnet.io import ensure_writable
    from fdnet.performance import timing
    from fdnet.version import __version__

    if json_path:
        ensure_writable(json_path, what="benchmark JSON")
    device = resolve_device(plan.device)
    torch.set_num_threads(plan.threads)
    try:
        import faiss

        faiss.omp_set_num_threads(plan.threads)
    except ImportError:  # pragma: no cover - faiss is a dependency
        pass
    cpu = timing.cpu_model()
    report: dict = {
        "threads": plan.threads,
        "machine": platform.processor() or platform.machine(),
        "cpu": cpu,
        "torch": torch.__version__,
        "fdnet": __version__,
        "device": str(device),
        "command": plan.command,
    }
    from fdnet.provenance import provenance

    # the synthetic inputs' seeds (the route, the random FDNet weights, the random maps and their revisits)
    report["provenance"] = provenance(
        plan.command,
        seeds={"synthetic_route": 0, "fdnet_weights": 0, "random_map": 0, "revisit_queries": 1},
        device=str(device),
    )
    out(
        f"fdnet benchmark: {plan.threads} threads, {cpu} ({platform.machine()}), torch {torch.__version__}, "
        f"device {device}"
    )
    _gemm_references(plan, report, out)
    lengths = [512] if plan.quick else plan.lengths
    if "fdnet" in plan.parts:
        _fdnet_extraction(plan, lengths, report, out)
    with _terminate_unwinds(), tempfile.TemporaryDirectory(prefix="fdnet-benchmark-") as workdir:
        if "api" in plan.parts:
            _public_api(plan, workdir, report, out)
        if "gpu" in plan.parts:
            _gpu(plan, device, workdir, report, out)
        if "matching" in plan.parts:
            _matching(plan, lengths, report, out)
        if "methods" in plan.parts:
            _methods(plan, report, out)
        if "scale" in plan.parts:
            _scale(plan, report, out)
        if "loop" in plan.parts:
            _loop(plan, workdir, report, out)
    if json_path:
        import json

        from fdnet.io import atomic_write_text

        atomic_write_text(json_path, json.dumps(report, indent=2, default=float))
        out(f"\nwrote {json_path}")
    return report


def _gemm_references(plan: BenchmarkPlan, report: dict, out) -> None:
    from fdnet.backbones import bf16_native
    from fdnet.performance import timing

    size = 1024 if plan.quick else 2048
    gflops = timing.gemm_gflops(size=size, repeats=plan.repeats)
    bf16_gflops = timing.gemm_gflops(size=size, repeats=plan.repeats, dtype="bf16")
    native = bf16_native("cpu")
    report.update(gemm_gflops_fp32=gflops, gemm_gflops_bf16=bf16_gflops, gemm_size=size, bf16_native_cpu=native)
    out(
        f"\nmachine references, measured now: fp32 GEMM {size}^3 = {gflops:.1f} GFLOP/s, bf16 GEMM = "
        f"{bf16_gflops:.1f} GFLOP/s ({'native' if native else 'no native'} bf16 on this CPU)"
    )


def _fdnet_extraction(plan: BenchmarkPlan, lengths, report: dict, out) -> None:
    from fdnet.methods.fdnet.config import preset
    from fdnet.paper import PAPER_TABLE2
    from fdnet.performance import timing

    gflops, bf16_gflops = report["gemm_gflops_fp32"], report["gemm_gflops_bf16"]
    paper_model = preset("paper").model
    out(
        "\nFDNet extraction, `paper` preset architecture (224x224, 5 blocks 64..512), ms/image; "
        "%GEMM = achieved GFLOP/s over the GEMM rate of the same precision"
    )
    out(
        f"{'L':>5} {'GFLOP':>6} {'fp32 b32':>9} {'bf16 b32':>9} {'bf16/fp32':>9} {'fp32 b1':>8} {'bf16 b1':>8} "
        f"{'%fp32GEMM':>9} {'%bf16GEMM':>9} {'paper GPU':>9} {'paper/ours':>10}"
    )
    report["fdnet_extraction_ms"] = {}
    for length in lengths:
        t = timing.fdnet_extraction(vector_length=length, repeats=plan.repeats)
        flops = timing.content_flops(dataclasses.replace(paper_model, vector_length=length))
        paper = PAPER_TABLE2.get(length, (float("nan"), float("nan")))[0]
        best = min(t["bf16_batch32"], t["fp32_batch32"])
        share_fp32 = flops / (t["fp32_batch32"] * 1e-3) / 1e9 / gflops
        share_bf16 = flops / (t["bf16_batch32"] * 1e-3) / 1e9 / bf16_gflops
        report["fdnet_extraction_ms"][length] = dict(
            t,
            paper_gpu=paper,
            gflop_per_image=flops / 1e9,
            fraction_of_fp32_gemm=share_fp32,
            fraction_of_bf16_gemm=share_bf16,
        )
        out(
            f"{length:>5} {flops / 1e9:>6.2f} {t['fp32_batch32']:>9.2f} {t['bf16_batch32']:>9.2f} "
            f"{t['fp32_batch32'] / t['bf16_batch32']:>8.2f}x {t['fp32_batch1']:>8.2f} {t['bf16_batch1']:>8.2f} "
            f"{100 * share_fp32:>8.0f}% {100 * share_bf16:>8.0f}% {paper:>9.1f} {paper / best:>9.2f}x"
        )


def _public_api(plan: BenchmarkPlan, workdir: str, report: dict, out) -> None:
    from fdnet.performance import timing

    run_dir, config = timing.temporary_fdnet_run(workdir, "cpu")
    flops = timing.content_flops(config.model)
    images = _images(plan, tuple(config.model.input_size), uint8=True)
    t = timing.descriptor_paths(run_dir, images, repeats=max(1, plan.repeats - 2), device="cpu", compiled=plan.compile)
    speedup = t["fp32_eager"] / t["extract"]
    rate = flops / (t["extract"] * 1e-3) / 1e9
    reference = report["gemm_gflops_bf16"] if t["extract_bf16"] else report["gemm_gflops_fp32"]
    report["cpu_preset_descriptor_ms"] = dict(
        t,
        gflop_per_image=flops / 1e9,
        speedup=speedup,
        fraction_of_gemm=rate / reference,
        input_size=list(config.model.input_size),
        vector_length=config.model.vector_length,
        images=len(images),
    )
    out(
        f"\nFDNet `cpu` preset descriptor through the public API (trunk + encoders, "
        f"{config.model.input_size[0]}x{config.model.input_size[1]}, L = {config.model.vector_length}, "
        f"{flops / 1e9:.2f} GFLOP/image), {len(images)} images, CPU, ms/image:"
    )
    out(f"  fp32 eager (float32 images, no autocast)   {t['fp32_eager']:8.2f}")
    out(
        f"  every command's default (uint8, fp32)      {t['fp32']:8.2f}   in forward passes of "
        f"{t['fp32_images_per_pass']} images (sized to the CPU's cache): {t['fp32_one_pass'] / t['fp32']:.2f}x "
        f"all {len(images)} in one pass ({t['fp32_one_pass']:.2f}); one image a call (a robot node): "
        f"{t['fp32_one']:.2f}"
    )
    out(
        f"  {'fdnet extract --bf16 (uint8, bf16)' if t['extract_bf16'] else 'native bf16 absent: fp32 (uint8)'}"
        "        "
        f"{t['extract']:8.2f}   {speedup:.2f}x the fp32 eager path, {rate:.1f} GFLOP/s = "
        f"{100 * rate / reference:.0f}% of the {'bf16' if t['extract_bf16'] else 'fp32'} GEMM rate; "
        f"paper FDNet_512 on a TITAN X 21.2 ms: {21.2 / t['extract']:.1f}x; one image a call: {t['extract_one']:.2f}"
    )
    if "extract_compiled" in t:
        report["cpu_preset_descriptor_ms"]["speedup_compiled"] = t["fp32_eager"] / t["extract_compiled"]
        out(
            f"  fdnet extract --compile                     {t['extract_compiled']:8.2f}   "
            f"{t['fp32_eager'] / t['extract_compiled']:.2f}x the fp32 eager path (compiling took "
            f"{t['compile_seconds']:.0f} s)"
        )


def _gpu(plan: BenchmarkPlan, device, workdir: str, report: dict, out) -> None:
    from fdnet.performance import timing

    if device.type != "cuda":
        report["gpu"] = None
        out(f"\nGPU: none here (device {device}); GPU figures unmeasured")
        return
    g: dict = {
        "gemm_gflops_fp32": timing.gemm_gflops(size=8192, repeats=plan.repeats, device=device),
        "gemm_gflops_bf16": timing.gemm_gflops(size=8192, repeats=plan.repeats, dtype="bf16", device=device),
    }
    # the paper's architecture (224x224, the paper's own speed figure) and the `cpu` preset users train
    for name in ("paper", "cpu"):
        run_dir, config = timing.temporary_fdnet_run(workdir, name, vector_length=512)
        g[name] = timing.gpu_figures(device, run_dir, seconds=1.0 if plan.quick else 3.0)
        g["name"] = g[name]["name"]
        h, w = config.model.input_size
        out(
            f"\nGPU {g['name']} ({device}): GEMM 8192^3 fp32 {g['gemm_gflops_fp32'] / 1e3:.1f} TFLOP/s, "
            f"bf16 {g['gemm_gflops_bf16'] / 1e3:.1f} TFLOP/s; FDNet_512, `{name}` preset at {h}x{w}, images/s "
            "(paper: 1000 / 21.2 ms = 47 images/s on a TITAN X):"
        )
        for key, value in g[name].items():
            if key.endswith("_images_per_s"):
                out(f"  {key[: -len('_images_per_s')]:24s} {value:10.0f}   {value / (1000 / 21.2):8.0f}x the paper")
    report["gpu"] = g


def _matching(plan: BenchmarkPlan, lengths, report: dict, out) -> None:
    from fdnet.paper import PAPER_TABLE2
    from fdnet.performance import timing

    map_size = plan.map_sizes[0]
    out(f"\nMatching: best of {map_size} references per query, ms/query")
    out(
        f"{'L':>5} {'numpy 1q':>9} {'numpy batch':>11} {'faiss flat':>10} {'faiss hnsw':>10} {'paper':>9} "
        f"{'paper/ours':>10}"
    )
    report["matching_ms"] = {}
    for length in lengths:
        m = timing.matching_per_query(map_size, length)
        paper = PAPER_TABLE2.get(length, (float("nan"), float("nan")))[1]
        report["matching_ms"][length] = dict(m, paper_gpu=paper, map_size=map_size)
        out(
            f"{length:>5} {m['numpy_single']:>9.4f} {m['numpy_batched']:>11.4f} {m['faiss_flat']:>10.4f} "
            f"{m['faiss_hnsw']:>10.4f} {paper:>9.2f} {paper / m['numpy_single']:>9.1f}x"
        )


def _methods(plan: BenchmarkPlan, report: dict, out) -> None:
    from fdnet.descriptors import create
    from fdnet.errors import FdnetError
    from fdnet.paper import PAPER_TABLE5
    from fdnet.performance import timing

    methods = list(plan.methods) + [m for m in [*plan.checkpoints, *plan.weights] if m not in plan.methods]
    methods = list(dict.fromkeys(methods))
    out(
        f"\nExtraction through the descriptor interface, {plan.num_images} images, ms/image "
        f"(decoding excluded); vs SAD = SAD's time / method's; vs paper = the paper's Table 5 time / ours"
    )
    timings = report["method_extraction_ms"] = {}
    cache = {}
    for method in methods:
        try:
            descriptor = create(
                method, checkpoint=plan.checkpoints.get(method), weights=plan.weights.get(method), device="cpu"
            )
            size = tuple(descriptor.input_size)
            if size not in cache:
                cache[size] = _images(plan, size)
            images = cache[size]
            if descriptor.needs_fit:
                descriptor.fit(images)
            ms = timing.descriptor_extraction(descriptor, images, repeats=max(1, plan.repeats - 2))
        except FdnetError as exc:
            if method in plan.weights or method in plan.checkpoints:
                raise  # a model the user named that cannot run is an error, not a skipped row
            out(f"  {method:10s} skipped: {exc}")
            timings[method] = None
            continue
        timings[method] = ms
        paper = PAPER_TABLE5.get(method, (None, None))[0]
        vs_paper = f"  paper {paper:g} ms: {paper / ms:.1f}x" if paper else ""
        out(f"  {method:10s} {ms:9.3f} ms/image  ({descriptor.dim}-d, input {size[0]}x{size[1]}){vs_paper}")
    sad = timings.get("sad")
    for method, ms in timings.items():
        if ms:
            if sad:
                report.setdefault("ratio_vs_sad", {})[method] = sad / ms
            if method in PAPER_TABLE5:
                report.setdefault("ratio_vs_paper_table5", {})[method] = PAPER_TABLE5[method][0] / ms
    report["paper_table5"] = {k: {"extraction_ms": v[0], "matching_ms": v[1]} for k, v in PAPER_TABLE5.items()}


def _scale(plan: BenchmarkPlan, report: dict, out) -> None:
    from fdnet.performance import timing

    dim = plan.scale_dim
    if dim is None:
        dim = 512
        if "fdnet" in plan.checkpoints:
            from fdnet.methods.fdnet.config import FDNetRunConfig
            from fdnet.runs import load_config

            dim = int(load_config(plan.checkpoints["fdnet"], FDNetRunConfig).model.vector_length)
    report["scale"] = []
    for n in plan.map_sizes:
        out(
            f"\nScale: a map of {n:,} random unit {dim}-d vectors, {min(plan.queries, n)} queries = map "
            f"vectors + noise {plan.noise}; recall@1 against exact search"
        )
        vectors = timing.random_map(n, dim)
        queries = timing.revisit_queries(vectors, plan.queries, plan.noise)
        report["scale"] += timing.scale_rows(
            vectors, queries, plan.kinds, plan.overrides, source="random", log=out, sweep=plan.sweep
        )
        del vectors
    if plan.map_vectors:
        vectors = _read_vectors(plan.map_vectors, "map vectors")
        queries = (
            _read_vectors(plan.query_vectors, "query vectors")
            if plan.query_vectors
            else timing.revisit_queries(vectors, plan.queries, plan.noise)
        )
        if queries.shape[1] != vectors.shape[1]:
            raise ConfigError(f"--query-vectors are {queries.shape[1]}-d but --map-vectors " f"{vectors.shape[1]}-d")
        out(
            f"\nScale: {plan.map_vectors}, {len(vectors):,} real {vectors.shape[1]}-d vectors, "
            f"{len(queries)} queries"
        )
        report["scale"] += timing.scale_rows(
            vectors, queries, plan.kinds, plan.overrides, source=str(plan.map_vectors), log=out, sweep=plan.sweep
        )


def _loop(plan: BenchmarkPlan, workdir: str, report: dict, out) -> None:
    from fdnet.performance.loop_benchmark import DescribeMs, loop_rows

    # loop-closure describes frames in fp32 (the descriptor's default) and uint8, a batch a call;
    # a robot node one frame a call. extract's bf16 path is what `--method-set fdnet:bf16=true`
    # gives it, where the CPU runs bf16 natively
    measured = report.get("cpu_preset_descriptor_ms") or {}
    describe = DescribeMs(measured["fp32_one"], measured["fp32"]) if "fp32" in measured else None
    describe_bf16 = DescribeMs(measured["extract_one"], measured["extract"]) if measured.get("extract_bf16") else None
    route = 100 if plan.quick else 300
    out(
        f"\nLoop closure: a route of {route} places driven twice after an earlier session's map of random unit "
        f"512-d vectors; margin, sequences of 10, the default gates; ms per frame of the decision (median over the "
        f"revisits), exhaustive search against the index (fdnet.decisions.loop_search)"
        + (
            ""
            if describe is None
            else f"; frames/s with the FDNet descriptor measured above, fp32 (uint8 images) as loop-closure "
            f"runs it ({describe.one:.1f} ms an image one a call, {describe.batch:.1f} in batches)"
            + (
                ""
                if describe_bf16 is None
                else f" and with bf16 autocast ({describe_bf16.one:.1f} / {describe_bf16.batch:.1f} ms)"
            )
        )
    )
    report["loop"] = loop_rows(
        plan.loop_map_sizes,
        dim=512,
        route=route,
        noise=plan.noise,
        describe_ms=describe,
        log=out,
        workdir=workdir,
        describe_bf16_ms=describe_bf16,
    )
    if plan.loop_compressed_sizes:
        from fdnet.performance.compressed_benchmark import HEADLINE, compressed_rows

        out(HEADLINE)
        report["loop_compressed"] = compressed_rows(
            plan.loop_compressed_sizes,
            workdir,
            plan.loop_real_vectors,
            describe_ms=None if describe is None else describe.one,
            log=out,
        )
    _loop_per_frame(plan, workdir, report, out)


def _loop_per_frame(plan: BenchmarkPlan, workdir: str, report: dict, out) -> None:
    """The robot's path (one frame at a time) against the command's (batched) on the same frames."""
    from pathlib import Path

    from PIL import Image

    from fdnet.performance import timing
    from fdnet.performance.loop_benchmark import per_frame_rows

    run_dir = plan.checkpoints.get("fdnet") or timing.temporary_fdnet_run(workdir, "cpu")[0]
    folder = plan.images
    frames = 40 if plan.quick else 120
    if folder is None:
        from fdnet.data.synthetic import render_route

        folder = Path(workdir) / "loop-frames"
        folder.mkdir(exist_ok=True)
        rendered = render_route(frames=frames, conditions=("summer",), seed=0)["summer"]
        for i, image in enumerate(rendered):
            Image.fromarray((np.clip(image, 0, 1) * 255).round().astype(np.uint8)).save(folder / f"frame_{i:04d}.png")
    out(
        f"\nLoop closure, the robot's path: {folder}, FDNet ({run_dir}), frames/s of the command against "
        "LoopClosureDetector.process one frame at a time:"
    )
    report["loop_per_frame"] = per_frame_rows(run_dir, folder, frames=frames, repeats=2 if plan.quick else 3, log=out)
