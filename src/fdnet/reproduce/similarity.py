"""Experiment ``similarity`` (paper Fig. 8): the query x reference similarity matrix of every
method on every pair, with the ground-truth cells drawn over it (for aligned traverses, the
diagonal band) and each query's best match marked green (correct) or red (wrong).

The table gives what the picture shows in numbers: the mean score on true-match cells against
the mean elsewhere, in units of the spread elsewhere (how far the diagonal stands out).
"""

from __future__ import annotations

import numpy as np

from fdnet.reproduce.sections import Figure, Heading, Paragraph, Table, best_cells, finite_or_none, number, pair_name

NAME = "similarity"
TITLE = "Similarity matrices"
PAPER = "Fig. 8 (similarity matrices of the Nordland test sequences; the ground truth is the diagonal)"

COLUMNS = ("mean on true matches", "mean elsewhere", "contrast", "R@1")


def unavailable(ctx) -> str | None:
    return None


def _contrast(similarity: np.ndarray, truth: np.ndarray) -> dict:
    on, off = similarity[truth], similarity[~truth]
    spread = float(off.std()) if off.size > 1 else 0.0
    return {
        "mean_true": finite_or_none(on.mean()) if on.size else None,
        "mean_other": finite_or_none(off.mean()) if off.size else None,
        "contrast": finite_or_none((on.mean() - off.mean()) / spread) if on.size and off.size and spread > 0 else None,
    }


def run(ctx) -> dict:
    from fdnet.evaluation import plots

    plt = plots.pyplot()
    pairs = []
    for pair in ctx.pairs:
        handles = ctx.available()
        truth = pair.split.ground_truth.dense()
        columns = min(4, len(handles))
        rows = -(-len(handles) // columns)
        fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 4.0 * rows), squeeze=False)
        methods = []
        for ax, handle in zip(axes.flat, handles):
            similarity = ctx.similarity(handle, pair.split, pair.slug)
            result = ctx.result(handle, pair.split, pair.slug)
            plots.draw_similarity_matrix(ax, similarity, pair.split.ground_truth, best=result.retrieved[:, 0])
            ax.set_title(handle.label, fontsize="medium")
            methods.append(
                {
                    "method": handle.label,
                    **_contrast(similarity, truth),
                    "recall_at_1": result.metrics[ctx.protocol].recall_at_n[1],
                }
            )
        for ax in list(axes.flat)[len(handles) :]:
            ax.axis("off")
        fig.suptitle(
            f"{pair.label}: rows = queries, columns = references; white band = ground truth", fontsize="medium"
        )
        fig.tight_layout()
        figure = plots.save_figure(fig, ctx.figure_path(f"similarity_{pair.slug}.png"))
        pairs.append(
            {
                "reference": pair.reference,
                "query": pair.query,
                "ground_truth": pair.split.ground_truth.description,
                "shape": list(truth.shape),
                "methods": methods,
                "figure": ctx.relative(figure),
            }
        )
    return {"pairs": pairs, "skipped": ctx.skipped()}


def render(document: dict) -> list:
    blocks: list = [
        Paragraph(
            "Bright = similar. The ground-truth cells are drawn in translucent white (for frame-aligned "
            "conditions the diagonal band); a green dot marks a query's best match when it is correct, a red "
            "cross when it is wrong. Contrast = (mean on true matches - mean elsewhere) / standard deviation "
            "elsewhere: how far the diagonal stands out from the rest of the matrix."
        )
    ]
    for pair in document["pairs"]:
        name = pair_name(pair["query"], pair["reference"])
        blocks.append(Heading(f"{name} ({pair['shape'][0]} x {pair['shape'][1]}; " f"{pair['ground_truth']})"))
        rows = [
            [m["method"], m["mean_true"], m["mean_other"], m["contrast"], m["recall_at_1"]] for m in pair["methods"]
        ]
        marked = best_cells(rows, [3, 4])
        blocks.append(
            Table(
                ["method", *COLUMNS],
                [[r[0]] + [number(v) for v in r[1:]] for r in rows],
                f"{pair_name(pair['query'], pair['reference'])}: scores on and off the ground truth "
                f"(scales differ between methods; compare contrast)",
                marked,
            )
        )
        blocks.append(Figure(pair["figure"], f"Similarity matrices, {pair_name(pair['query'], pair['reference'])}"))
    return blocks
