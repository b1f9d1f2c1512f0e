"""Experiment ``runtime`` (paper Table 5): extraction ms/image and matching ms/query of every
method on this machine, the hardware named, the paper's TITAN X figures beside them as ratios.

Extraction is ``describe`` on images already decoded at the method's input size (median of
repeats after a warm-up, :func:`fdnet.performance.timing.descriptor_extraction`); matching is finding one
query's best reference by the method's own comparison over the first pair's vectors, queries one
at a time (:func:`ranking_ms_per_query`). Nothing here is asserted anywhere: it is measured and
reported, on whatever else the machine is doing.
"""

from __future__ import annotations

from fdnet.reproduce.sections import Figure, Paragraph, Table, number, pair_name

NAME = "runtime"
TITLE = "Runtime: extraction and matching"
PAPER = "Table 5 (ms/image extraction on a TITAN X GPU, ms/query matching), section 5.4"


def unavailable(ctx) -> str | None:
    return None


def ranking_ms_per_query(descriptor, queries, references, repeats: int = 3, max_queries: int = 50) -> float:
    """ms/query to find one query's best reference by ``descriptor.similarity`` (the method's own
    comparison) over vectors already described: queries one at a time, as the paper times
    "matching between reference and a single query image" (a batch of queries would share one
    matrix product and hide the per-query cost)."""
    from fdnet.matching.similarity import top_k
    from fdnet.performance.timing import median_seconds

    chosen = queries[:max_queries]

    def one_at_a_time() -> None:
        for query in chosen:
            top_k(query[None], references, 1, similarity=descriptor.similarity)

    return median_seconds(one_at_a_time, repeats=repeats) / max(len(chosen), 1) * 1e3


def machine_description() -> dict:
    """What the timings ran on: CPU model, logical cores, torch threads, GPU (if any), OS."""
    import os
    import platform

    import torch
    from threadpoolctl import threadpool_info

    from fdnet.performance.timing import cpu_model

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    blas = [pool["num_threads"] for pool in threadpool_info() if pool.get("user_api") == "blas"]
    return {
        "cpu": cpu_model(),
        "logical_cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "blas_threads": max(blas) if blas else None,
        "gpu": gpu,
        "platform": platform.platform(),
    }


def _ratio(paper: float | None, ours: float | None) -> float | None:
    return paper / ours if paper and ours else None


def run(ctx) -> dict:
    from fdnet.data.images import load_images
    from fdnet.paper import PAPER_HARDWARE, paper_runtime
    from fdnet.performance import timing

    pair = ctx.pairs[0]
    split = pair.split
    paths = split.query.paths[: ctx.settings.runtime_images]
    images_by_size: dict = {}
    methods = []
    for handle in ctx.available():
        ctx.log(f"[{NAME}] timing {handle.label}")
        descriptor = handle.fitted(split.reference.paths)
        size = tuple(descriptor.input_size)
        if size not in images_by_size:
            images_by_size[size] = load_images(paths, size)
        descriptor.describe(images_by_size[size][:1])  # loads what the method loads on first use
        ctx.limit_threads()
        ms_image = timing.descriptor_extraction(descriptor, images_by_size[size], repeats=3)
        queries, references = ctx.pair_vectors(handle, split)
        ms_query = ranking_ms_per_query(descriptor, queries, references)
        paper = paper_runtime(handle.name) or {}
        methods.append(
            {
                "method": handle.label,
                "dim": int(descriptor.dim),
                "input_size": list(size),
                "ms_per_image": ms_image,
                "ms_per_query": ms_query,
                "paper_name": paper.get("paper_name"),
                "paper_ms_per_image": paper.get("ms_per_image"),
                "paper_ms_per_query": paper.get("ms_per_query"),
                "extraction_ratio_paper_over_ours": _ratio(paper.get("ms_per_image"), ms_image),
                "matching_ratio_paper_over_ours": _ratio(paper.get("ms_per_query"), ms_query),
            }
        )
    figure = _bars(ctx, methods)
    return {
        "machine": machine_description(),
        "gemm_gflops_fp32": timing.gemm_gflops(repeats=3),
        "reference": pair.reference,
        "query": pair.query,
        "num_images_timed": len(paths),
        "num_queries": len(split.query),
        "map_size": len(split.reference),
        "methods": methods,
        "paper_hardware": PAPER_HARDWARE,
        "figure": ctx.relative(figure),
        "skipped": ctx.skipped(),
    }


def _bars(ctx, methods: list[dict]):
    """Ours beside the paper's, per method, on a log scale (times span four orders of magnitude)."""
    import numpy as np

    from fdnet.evaluation import plots

    plt = plots.pyplot()
    names = [m["method"] for m in methods]
    y = np.arange(len(names))
    fig, axes = plt.subplots(1, 2, figsize=(11, 0.45 * len(names) + 1.6), squeeze=False)
    for ax, key, title in (
        (axes[0, 0], "ms_per_image", "extraction, ms/image"),
        (axes[0, 1], "ms_per_query", "matching, ms/query"),
    ):
        ours = [m[key] for m in methods]
        paper = [m[f"paper_{key}"] or 0.0 for m in methods]
        ax.barh(y - 0.2, ours, height=0.4, label="this machine")
        ax.barh(y + 0.2, paper, height=0.4, label="paper (Table 5)")
        ax.set_yticks(y, names)
        ax.invert_yaxis()
        ax.set_xscale("log")
        ax.set_title(title, fontsize="medium")
        ax.grid(axis="x", alpha=0.3)
    axes[0, 0].legend(fontsize="small")
    fig.tight_layout()
    return plots.save_figure(fig, ctx.figure_path("runtime.png"))


def render(document: dict) -> list:
    machine = document["machine"]
    gpu = machine.get("gpu") or "none"
    blocks: list = [
        Paragraph(
            f"This machine: {machine['cpu']}, {machine['logical_cores']} logical cores, "
            f"{machine['torch_threads']} torch threads, {machine.get('blas_threads') or '?'} BLAS threads, "
            f"GPU: {gpu} (descriptors run on the CPU unless a "
            f"method's device setting says otherwise); {machine['platform']}; fp32 GEMM "
            f"{document['gemm_gflops_fp32']:.1f} GFLOP/s."
        ),
        Paragraph(
            f"Extraction: median ms/image over {document['num_images_timed']} decoded images of "
            f"{document['query']}; matching: ms/query to rank a map of {document['map_size']} references "
            f"for one query at a time "
            f"({pair_name(document['query'], document['reference'])}). "
            f"Paper: {document['paper_hardware']}. Ratio = paper / ours, so above 1 means faster here."
        ),
    ]
    rows = []
    for m in document["methods"]:
        rows.append(
            [
                m["method"],
                str(m["dim"]),
                "x".join(str(v) for v in m["input_size"]),
                number(m["ms_per_image"], 2),
                number(m["ms_per_query"], 4),
                m["paper_name"] or "-",
                number(m["paper_ms_per_image"], 1),
                number(m["extraction_ratio_paper_over_ours"], 2),
                number(m["paper_ms_per_query"], 3),
                number(m["matching_ratio_paper_over_ours"], 2),
            ]
        )
    blocks.append(
        Table(
            [
                "method",
                "dim",
                "input (HxW)",
                "ms/image",
                "ms/query",
                "paper row",
                "paper ms/image (TITAN X)",
                "paper / ours",
                "paper ms/query",
                "paper / ours",
            ],
            rows,
            "Extraction and matching time per method",
        )
    )
    blocks.append(
        Figure(
            document["figure"],
            "Extraction and matching time per method, this machine beside the "
            "paper's Table 5 (log scale; no bar where the paper has no figure)",
        )
    )
    if any(m["method"] == "fdnet" and m["dim"] != 512 for m in document["methods"]):
        blocks.append(
            Paragraph(
                "The paper's FDNet row is L = 512; this run's FDNet has the length in the dim "
                "column (see the lengths section for each L).",
                note=True,
            )
        )
    return blocks
