"""Experiment ``viewpoint`` (paper Figs 18, 19): simulated viewpoint change.

As the paper does (after Sünderhauf et al.): reference and query images are cropped to half their
width; the reference crop is the left half, the query crop is shifted right so that it overlaps
the reference crop by 100, 90, 75 and 65 % (shift = (1 - overlap) x half width). Every method is
evaluated at every overlap (PR curves, R@1, R@100P; paper Fig. 18), and FDNet's content and
appearance vectors of each shifted query crop are compared with those of its unshifted crop
(paper Fig. 19: the content vector moves, the appearance vector should not).

The crops are written once as PNG files under ``OUT/cache/crops/`` (wider crops are scaled to
``MAX_CROP_WIDTH`` pixels: every method reads far smaller images), so the descriptor cache and
every method's own image loading apply to them unchanged. The pair is the first ordered pair, or
``viewpoint_pair`` (reference, query).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from fdnet.errors import ConfigError
from fdnet.reproduce.sections import Figure, Heading, Paragraph, Table, best_cells, number

NAME = "viewpoint"
TITLE = "Viewpoint shift: half-width crops at 100/90/75/65% overlap"
PAPER = (
    "Fig. 18 (PR curves per overlap, Nordland summer vs winter), Fig. 19 (response of content and appearance "
    "vectors to the shift), section 5.3"
)

MAX_CROP_WIDTH = 640
#: components of v_c and v_a drawn for the example place (all of them when shorter)
PLOTTED_COMPONENTS = 128


def unavailable(ctx) -> str | None:
    _pair(ctx)  # a --viewpoint-pair that is not among the pairs is an error before any work
    return None


def crop_columns(width: int, overlap: float) -> tuple[int, int]:
    """[left, right) columns of a half-width crop overlapping the left half by ``overlap``."""
    half = width // 2
    shift = int(round((1.0 - overlap) * half))
    return shift, shift + half


def write_crops(traverse, overlap: float, folder: Path) -> list[Path]:
    """Half-width crops of every image of ``traverse`` at ``overlap`` into ``folder`` (kept when a
    previous run wrote them from the same images), in the traverse's order."""
    from PIL import Image

    from fdnet.data.images import load_image
    from fdnet.io import atomic_path, atomic_write_text
    from fdnet.reproduce.cache import image_list_key

    targets = [folder / f"{i:06d}_{Path(p).stem}.png" for i, p in enumerate(traverse.paths)]
    stamp = folder / "sources.json"
    source = {"images": image_list_key(traverse.paths), "overlap": overlap, "max_width": MAX_CROP_WIDTH}
    if stamp.is_file() and json.loads(stamp.read_text()) == source and all(t.is_file() for t in targets):
        return targets
    for path, target in zip(traverse.paths, targets):
        image = load_image(path)
        left, right = crop_columns(image.shape[1], overlap)
        crop = Image.fromarray(np.round(image[:, left:right] * 255).astype(np.uint8))
        if crop.width > MAX_CROP_WIDTH:
            crop = crop.resize(
                (MAX_CROP_WIDTH, max(1, round(crop.height * MAX_CROP_WIDTH / crop.width))), Image.Resampling.BOX
            )
        with atomic_path(target) as tmp:
            crop.save(tmp, format="PNG")
    atomic_write_text(stamp, json.dumps(source) + "\n")
    return targets


def _pair(ctx):
    wanted = ctx.settings.viewpoint_pair
    if wanted is None:
        return ctx.pairs[0]
    for pair in ctx.pairs:
        if (pair.reference, pair.query) == tuple(wanted):
            return pair
    raise ConfigError(
        f"--viewpoint-pair {wanted[0]},{wanted[1]}: no such pair among "
        f"{'; '.join(f'{p.reference},{p.query}' for p in ctx.pairs)} (REFERENCE,QUERY)"
    )


def _cosine_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    b = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    return np.clip(1.0 - (a * b).sum(axis=1), 0.0, 2.0)  # rounding can dip just below 0


def run(ctx) -> dict:
    from fdnet.data.dataset import Traverse
    from fdnet.data.images import load_image
    from fdnet.data.split import EvaluationSplit
    from fdnet.evaluation import plots
    from fdnet.reproduce.context import matched_reference

    pair = _pair(ctx)
    reference, query = pair.split.reference, pair.split.query
    crops = ctx.out / "cache" / "crops"

    def cropped(traverse, overlap):
        folder = crops / pair.slug / f"{traverse.name}_{round(overlap * 100):03d}"
        return Traverse(
            f"{traverse.name} crops at {overlap:.0%}",
            write_crops(traverse, overlap, folder),
            frame_ids=traverse.frame_ids,
        )

    ctx.log(f"[{NAME}] writing half-width crops of {pair.label}")
    reference_crops = cropped(reference, 1.0)
    query_crops = {overlap: cropped(query, overlap) for overlap in sorted({1.0, *ctx.settings.overlaps}, reverse=True)}
    overlaps = list(ctx.settings.overlaps)
    splits = {
        o: EvaluationSplit(
            reference_crops,
            query_crops[o],
            pair.split.ground_truth,
            f"{pair.split.description}; half-width crops, query at {o:.0%} overlap",
        )
        for o in overlaps
    }

    methods, curves = [], {o: {} for o in overlaps}
    for handle in ctx.available():
        row = {"method": handle.label, "overlaps": []}
        for o in overlaps:
            result = ctx.result(handle, splits[o], f"viewpoint_{round(o * 100)}_{pair.slug}")
            metrics = result.metrics[ctx.protocol]
            curves[o][handle.label] = (metrics.curve, metrics.auc_pr)
            row["overlaps"].append(
                {
                    "overlap": o,
                    "recall_at_1": metrics.recall_at_n[1],
                    "recall_at_100_precision": metrics.recall_at_100_precision,
                    "auc_pr": metrics.auc_pr,
                }
            )
        methods.append(row)

    plt = plots.pyplot()
    fig, axes = plt.subplots(1, len(overlaps), figsize=(4.6 * len(overlaps), 4.3), squeeze=False)
    for ax, o in zip(axes[0], overlaps):
        plots.draw_pr_curves(ax, curves[o])
        ax.get_legend().remove()
        ax.set_title(f"{o:.0%} overlap", fontsize="medium")
    # one legend of method names for every panel, beside them (each panel's own would cover curves)
    handles, _ = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, list(curves[overlaps[0]]), loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize="small")
    fig.suptitle(f"{pair.label}, half-width crops ({ctx.protocol_label})", fontsize="medium")
    fig.tight_layout()
    pr_figure = plots.save_figure(fig, ctx.figure_path(f"pr_{pair.slug}.png"))

    with_match = [q for q in range(len(query)) if matched_reference(pair.split, q) is not None]
    example = with_match[len(with_match) // 2] if with_match else len(query) // 2
    example_reference = matched_reference(pair.split, example)
    shown = [
        (
            f"reference {reference.name}",
            reference_crops.paths[example if example_reference is None else example_reference],
        )
    ]
    shown += [(f"query {query.name}, {o:.0%}", query_crops[o].paths[example]) for o in overlaps]
    fig, axes = plt.subplots(1, len(shown), figsize=(2.4 * len(shown), 2.8), squeeze=False)
    for ax, (label, path) in zip(axes[0], shown):
        ax.imshow(load_image(path))
        ax.set_title(label, fontsize="x-small")
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    crops_figure = plots.save_figure(fig, ctx.figure_path(f"crops_{pair.slug}.png"))

    response = _response(ctx, query_crops, overlaps, example, plt, plots, pair)
    return {
        "reference": pair.reference,
        "query": pair.query,
        "ground_truth": pair.split.ground_truth.description,
        "num_queries": len(query),
        "overlaps": overlaps,
        "methods": methods,
        "example_query": query.paths[example].name,
        "pr_figure": ctx.relative(pr_figure),
        "crops_figure": ctx.relative(crops_figure),
        "response": response,
        "skipped": ctx.skipped(),
    }


def _response(ctx, query_crops: dict, overlaps: list, example: int, plt, plots, pair) -> dict | None:
    """FDNet's v_c and v_a of every shifted query crop against its unshifted crop (Fig. 19)."""
    handle = ctx.handles.get("fdnet")
    if handle is None or not handle.available or not hasattr(handle.descriptor, "describe_appearance"):
        return None
    vectors = {}
    for o, crops in query_crops.items():
        vectors[o] = (
            ctx.vectors(handle, crops.paths, what=crops.name),
            ctx.vectors(handle, crops.paths, kind="appearance", what=crops.name),
        )
    rows = []
    for o in overlaps:
        content, appearance = vectors[o]
        content0, appearance0 = vectors[1.0]
        relative = np.linalg.norm(appearance - appearance0, axis=1) / np.maximum(
            np.linalg.norm(appearance0, axis=1), 1e-12
        )
        rows.append(
            {
                "overlap": o,
                "content_cosine_distance": float(_cosine_distance(content, content0).mean()),
                "appearance_cosine_distance": float(_cosine_distance(appearance, appearance0).mean()),
                "appearance_relative_change": float(relative.mean()),
                "content_relative_change": float(np.linalg.norm(content - content0, axis=1).mean()),
            }
        )
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.4))
    for o in overlaps:
        content, appearance = vectors[o]
        components = min(PLOTTED_COMPONENTS, content.shape[1])
        axes[0].plot(content[example, :components], linewidth=1, label=f"{o:.0%}")
        axes[1].plot(appearance[example, : min(PLOTTED_COMPONENTS, appearance.shape[1])], linewidth=1, label=f"{o:.0%}")
    axes[0].set_title(f"content vector v_c of query {example} ({pair.query}) at each overlap", fontsize="medium")
    axes[1].set_title("appearance vector v_a at each overlap", fontsize="medium")
    for ax in axes:
        ax.legend(fontsize="x-small", loc="upper right")
    axes[1].set_xlabel(f"component (first {PLOTTED_COMPONENTS} at most)")
    fig.tight_layout()
    figure = plots.save_figure(fig, ctx.figure_path(f"response_{pair.slug}.png"))
    return {"rows": rows, "figure": ctx.relative(figure)}


def render(document: dict) -> list:
    overlaps = document["overlaps"]
    blocks: list = [
        Paragraph(
            f"{document['query']} queries against {document['reference']} references ({document['num_queries']} "
            f"queries, {document['ground_truth']}). Both cropped to half width; the query crop is shifted right to "
            f"overlap the reference crop by {', '.join(f'{o:.0%}' for o in overlaps)}."
        )
    ]
    header = ["method"] + [f"R@1 {o:.0%}" for o in overlaps] + [f"R@100P {o:.0%}" for o in overlaps]
    rows = [
        [m["method"]]
        + [e["recall_at_1"] for e in m["overlaps"]]
        + [e["recall_at_100_precision"] for e in m["overlaps"]]
        for m in document["methods"]
    ]
    marked = best_cells(rows, list(range(1, len(header))))
    blocks.append(
        Table(
            header,
            [[r[0]] + [number(v) for v in r[1:]] for r in rows],
            "R@1 and R@100P per overlap (paper protocol)",
            marked,
        )
    )
    blocks.append(
        Figure(
            document["crops_figure"],
            f"Reference crop and the query crops of {document['example_query']} " f"at each overlap",
        )
    )
    blocks.append(Figure(document["pr_figure"], "PR curves per overlap, every method"))
    response = document.get("response")
    blocks.append(Heading("How FDNet's content and appearance vectors respond to the shift (Fig. 19)"))
    if response is None:
        blocks.append(Paragraph("FDNet did not run, so its vectors' response is not shown.", note=True))
        return blocks
    blocks.append(
        Table(
            [
                "overlap",
                "v_c cosine distance to 100%",
                "|dv_c| (unit vectors)",
                "v_a cosine distance to 100%",
                "|dv_a| / |v_a|",
            ],
            [
                [
                    f"{r['overlap']:.0%}",
                    number(r["content_cosine_distance"], 4),
                    number(r["content_relative_change"], 4),
                    number(r["appearance_cosine_distance"], 4),
                    number(r["appearance_relative_change"], 4),
                ]
                for r in response["rows"]
            ],
            "Mean change of each query crop's vectors against its unshifted crop: the paper finds that "
            "the content vector changes and the appearance vector does not",
        )
    )
    blocks.append(
        Figure(response["figure"], "Content (top) and appearance (bottom) vector of one query crop at " "each overlap")
    )
    return blocks
