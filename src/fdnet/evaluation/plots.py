"""Figures: PR curves of several methods, a similarity matrix with its ground truth, example matches.

matplotlib with the non-interactive Agg backend (no display needed); every PNG is written
atomically. The similarity matrix figure follows the paper's Fig. 8 (queries x references, bright =
similar) with the ground truth drawn over it; the example grid follows VPR_Tutorial's
``show_correct_and_wrong_matches`` (query beside its best match, framed green if correct, red if not),
and with several methods the paper's Fig. 9 (a row per method). The ``draw_*`` functions draw on
one axis so multi-panel figures (``fdnet reproduce``) reuse them.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from fdnet.data.groundtruth import GroundTruth
from fdnet.io import atomic_path


def pyplot():
    """matplotlib.pyplot on the Agg backend (imported here so plotting stays an optional cost)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | os.PathLike) -> Path:
    """Write ``fig`` atomically and close it: PNG, or JPEG when ``path`` ends in .jpg/.jpeg (for
    grids of photographs, a fraction of the PNG's bytes)."""
    plt = pyplot()
    path = Path(path)
    jpeg = path.suffix.lower() in (".jpg", ".jpeg")
    with atomic_path(path) as tmp:
        fig.savefig(
            tmp,
            format="jpeg" if jpeg else "png",
            dpi=110,
            bbox_inches="tight",
            **({"pil_kwargs": {"quality": 85}} if jpeg else {}),
        )
    plt.close(fig)
    return path


def draw_pr_curves(ax, curves: dict) -> None:
    """Several methods' PR curves on one matplotlib axis (see :func:`plot_pr_curves`)."""
    for name, entry in curves.items():
        label = name
        if isinstance(entry, tuple) and len(entry) == 2 and hasattr(entry[0], "recall"):
            entry, auc = entry
            label = f"{name} (AUC {auc:.3f})"
        recall, precision = (entry.recall, entry.precision) if hasattr(entry, "recall") else entry
        ax.plot(recall, precision, label=label, drawstyle="default")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize="small")


def plot_pr_curves(curves: dict, path: str | os.PathLike, title: str = "") -> Path:
    """Several methods' PR curves on one figure.

    ``curves``: method name -> :class:`~fdnet.metrics.PRCurve` (or a ``(recall,
    precision)`` pair); the legend shows each method's AUC when given as ``{name: (curve, auc)}``.
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    draw_pr_curves(ax, curves)
    if title:
        ax.set_title(title, fontsize="medium")
    return save_figure(fig, path)


def draw_similarity_matrix(
    ax, similarity: np.ndarray, ground_truth: GroundTruth | None = None, best: np.ndarray | None = None
):
    """The (Q, R) matrix on one matplotlib axis (see :func:`plot_similarity_matrix`); returns the
    image, for a colour bar. Beyond ~300 rows or columns a cell is smaller than a screen pixel, so
    the ground-truth cells are widened until the true-match band stays visible."""
    s = np.asarray(similarity, dtype=np.float32)
    image = ax.imshow(s, cmap="viridis", aspect="auto", interpolation="nearest")
    if ground_truth is not None:
        gt = ground_truth.dense()
        widen = int(np.ceil(max(gt.shape) / 300))
        if widen > 1:
            from scipy.ndimage import maximum_filter

            gt = maximum_filter(gt, size=widen)
        overlay = np.zeros((*gt.shape, 4), dtype=np.float32)
        overlay[..., :3] = 1.0
        overlay[..., 3] = 0.35 * gt.astype(np.float32)
        ax.imshow(overlay, aspect="auto", interpolation="nearest")
    if best is not None:
        best = np.asarray(best).reshape(-1)
        rows = np.arange(len(best))
        if ground_truth is not None:
            ok = ground_truth.correct_mask(best[:, None])[:, 0]
            ax.scatter(best[ok], rows[ok], s=6, c="lime", marker="o", label="best match, correct")
            ax.scatter(best[~ok], rows[~ok], s=8, c="red", marker="x", label="best match, wrong")
            ax.legend(loc="upper right", fontsize="x-small")
        else:
            ax.scatter(best, rows, s=6, c="white", marker="o")
    ax.set_xlabel("reference")
    ax.set_ylabel("query")
    return image


def plot_similarity_matrix(
    similarity: np.ndarray,
    path: str | os.PathLike,
    ground_truth: GroundTruth | None = None,
    best: np.ndarray | None = None,
    title: str = "",
) -> Path:
    """The (Q, R) matrix as an image (rows = queries), ground-truth cells outlined in translucent
    white and each query's best match marked: green dot if correct, red cross if not."""
    plt = pyplot()
    s = np.asarray(similarity, dtype=np.float32)
    fig, ax = plt.subplots(figsize=(6, 6 * min(max(s.shape[0] / max(s.shape[1], 1), 0.3), 3)))
    image = draw_similarity_matrix(ax, s, ground_truth, best)
    fig.colorbar(image, ax=ax, fraction=0.046, pad=0.04, label="similarity")
    if title:
        ax.set_title(title, fontsize="medium")
    return save_figure(fig, path)


def evenly_spaced(total: int, count: int) -> np.ndarray:
    """``count`` indices spread evenly over ``range(total)``, first and last included (the queries
    an example figure shows)."""
    count = max(1, min(count, total))
    return np.unique(np.linspace(0, total - 1, count).round().astype(int))


def plot_match_grid(
    query_paths: Sequence[str | os.PathLike],
    reference_paths: Sequence[str | os.PathLike],
    matches: dict[str, tuple[np.ndarray, np.ndarray]],
    path: str | os.PathLike,
    count: int = 6,
    title: str = "",
    image_size: tuple[int, int] = (120, 160),
) -> Path:
    """``count`` queries (evenly spaced over the traverse) in columns: the query on top, then one
    row per method (``matches``: method -> (best reference per query, correct per query)) with
    that method's best match, framed green if correct and red if not (the paper's Fig. 9)."""
    from fdnet.data.images import load_image

    plt = pyplot()
    chosen = evenly_spaced(len(query_paths), count)
    rows = [
        (method, np.asarray(best).reshape(-1), np.asarray(correct, dtype=bool).reshape(-1))
        for method, (best, correct) in matches.items()
    ]
    fig, axes = plt.subplots(
        1 + len(rows), len(chosen), figsize=(2.2 * len(chosen), 2.1 * (1 + len(rows))), squeeze=False
    )
    for col, q in enumerate(chosen):
        cells = [(query_paths[q], f"query {q}", None)]
        for _, best, correct in rows:
            colour, verdict = ("limegreen", "correct") if correct[q] else ("red", "wrong")
            cells.append((reference_paths[best[q]], f"best: ref {best[q]} ({verdict})", colour))
        for row, (image_path, label, colour) in enumerate(cells):
            ax = axes[row, col]
            ax.imshow(load_image(image_path, image_size))
            ax.set_title(label, fontsize="x-small")
            ax.set_xticks([])
            ax.set_yticks([])
            if colour is not None:
                for spine in ax.spines.values():
                    spine.set_edgecolor(colour)
                    spine.set_linewidth(4)
    for row, (method, _, _) in enumerate(rows, start=1):
        if method:
            axes[row, 0].set_ylabel(method, fontsize="small")
    if title:
        fig.suptitle(title, fontsize="medium")
    fig.tight_layout()  # else a tall grid leaves a wide gap under the title
    return save_figure(fig, path)


def plot_example_matches(
    query_paths: Sequence[str | os.PathLike],
    reference_paths: Sequence[str | os.PathLike],
    best: np.ndarray,
    correct: np.ndarray,
    path: str | os.PathLike,
    count: int = 6,
    title: str = "",
    image_size: tuple[int, int] = (120, 160),
) -> Path:
    """A grid of ``count`` queries (evenly spaced over the traverse): query on top, its best match
    below, framed green if the match is correct and red if not."""
    return plot_match_grid(query_paths, reference_paths, {"": (best, correct)}, path, count, title, image_size)


def _file_safe(name: str) -> str:
    import re

    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name) or "method"


def write_result_plots(results, protocol: str, folder: str | os.PathLike, examples: int = 6) -> list[Path]:
    """The figures of ``fdnet evaluate --plots``: every result's PR curve in one plot, and per
    result its similarity matrix (when kept) and example matches (when its images are known)."""
    folder = Path(folder)
    written = [
        plot_pr_curves(
            {r.method: (r.metrics[protocol].curve, r.metrics[protocol].auc_pr) for r in results},
            folder / "pr_curves.png",
            title=f"{results[0].dataset or 'PR curves'} [{protocol}]",
        )
    ]
    for r in results:
        if r.similarity is not None:
            written.append(
                plot_similarity_matrix(
                    r.similarity,
                    folder / f"similarity_{_file_safe(r.method)}.png",
                    r.ground_truth,
                    best=r.retrieved[:, 0],
                    title=r.method,
                )
            )
        if r.query_paths is not None and r.reference_paths is not None:
            correct = r.ground_truth.correct_mask(r.retrieved[:, :1])[:, 0]
            written.append(
                plot_example_matches(
                    r.query_paths,
                    r.reference_paths,
                    r.retrieved[:, 0],
                    correct,
                    folder / f"matches_{_file_safe(r.method)}.png",
                    count=examples,
                    title=f"{r.method}: query (top) and best match",
                )
            )
    return written
