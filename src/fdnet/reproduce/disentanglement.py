"""Experiment ``disentanglement`` (paper Figs 10-13): does FDNet's content vector keep the place and
its appearance vector the condition?

* Fig. 11: histograms of the element-wise |v_c(x) - v_c(y)| of unit content vectors, for x and y the
  same place under two conditions against x and y different places; with the share of same-place
  pairs whose mean difference is below a different-place pair's (the area under the ROC curve).
* Fig. 12: the appearance vectors v_a of a few places under every condition.
* Fig. 13: 2-D embeddings (PCA and t-SNE, scikit-learn) of appearance and of content vectors,
  coloured by condition, each with its silhouette score by condition (in the 2-D embedding and in
  the full vectors). What one should see: appearance separates the conditions (silhouette near 1),
  content does not (near 0 or below).
"""

from __future__ import annotations

import numpy as np

from fdnet.reproduce.context import condition_traverses, matched_reference
from fdnet.reproduce.sections import Figure, Heading, Paragraph, Table, finite_or_none, number

NAME = "disentanglement"
TITLE = "Content vs appearance (disentanglement)"
PAPER = (
    "Fig. 11 (|content difference| histograms, same vs different place), Fig. 12 (appearance vectors per "
    "place and season), Fig. 13 (2-D embedding of appearance vectors by condition)"
)

#: the paper's reading of Fig. 11: same-place differences stay below 0.05
PAPER_THRESHOLD = 0.05
#: appearance-vector components drawn per place (all of them when the vector is shorter)
PLOTTED_COMPONENTS = 128
PLACES_SHOWN = 3


def unavailable(ctx) -> str | None:
    handle = ctx.handles.get("fdnet")
    if handle is None:
        return "needs FDNet (add fdnet to --method, with --checkpoint RUN_DIR)"
    if not handle.available:
        return f"FDNet cannot run here: {handle.reason}"
    if not hasattr(handle.descriptor, "describe_appearance"):
        return "this FDNet descriptor has no appearance encoder (describe_appearance)"
    return None


def _unordered_pairs(pairs) -> list:
    seen, out = set(), []
    for pair in pairs:
        key = frozenset((pair.reference, pair.query))
        if key not in seen:
            seen.add(key)
            out.append(pair)
    return out


def _place_pairs(split, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(queries, their same-place references, a random different-place reference each)."""
    queries, same, other = [], [], []
    num_refs = split.ground_truth.num_references
    for q in range(split.ground_truth.num_queries):
        r = matched_reference(split, q)
        if r is None:
            continue
        wrong = np.setdiff1d(np.arange(num_refs), split.ground_truth.positives[q])
        if not len(wrong):
            continue
        queries.append(q)
        same.append(r)
        other.append(int(rng.choice(wrong)))
    return np.array(queries, dtype=int), np.array(same, dtype=int), np.array(other, dtype=int)


def _content_differences(ctx, handle, pair, rng) -> dict:
    from sklearn.metrics import roc_auc_score

    split = pair.split
    q_vecs, r_vecs = ctx.pair_vectors(handle, split)
    a_q = ctx.vectors(handle, split.query.paths, kind="appearance", what=split.query.name)
    a_r = ctx.vectors(handle, split.reference.paths, kind="appearance", what=split.reference.name)
    queries, same, other = _place_pairs(split, rng)
    if len(queries) < 2:
        return {"reference": pair.reference, "query": pair.query, "num_places": int(len(queries))}
    same_diff = np.abs(q_vecs[queries] - r_vecs[same])
    other_diff = np.abs(q_vecs[queries] - r_vecs[other])
    same_mean, other_mean = same_diff.mean(axis=1), other_diff.mean(axis=1)
    labels = np.r_[np.ones(len(queries)), np.zeros(len(queries))]
    auc = roc_auc_score(labels, -np.r_[same_mean, other_mean])

    # Distances between whole vectors: a place under another condition vs another place under
    # the same condition. Content should keep the place (first smaller), appearance the condition.
    shuffled = rng.permutation(len(queries))

    def distances(query_vectors, reference_vectors) -> dict:
        across = np.linalg.norm(query_vectors[queries] - reference_vectors[same], axis=1)
        within = np.linalg.norm(query_vectors[queries] - query_vectors[queries[shuffled]], axis=1)
        distinct = queries != queries[shuffled]
        return {
            "same_place_other_condition": finite_or_none(across.mean()),
            "other_place_same_condition": finite_or_none(within[distinct].mean()) if distinct.any() else None,
        }

    return {
        "reference": pair.reference,
        "query": pair.query,
        "num_places": int(len(queries)),
        "mean_abs_difference_same_place": float(same_diff.mean()),
        "mean_abs_difference_other_place": float(other_diff.mean()),
        "share_below_threshold_same_place": float((same_diff < PAPER_THRESHOLD).mean()),
        "share_below_threshold_other_place": float((other_diff < PAPER_THRESHOLD).mean()),
        "same_place_closer_auc": float(auc),
        "content_distances": distances(q_vecs, r_vecs),
        "appearance_distances": distances(a_q, a_r),
        "_histograms": (same_diff.ravel(), other_diff.ravel()),
    }


def _embeddings(vectors: dict[str, np.ndarray], max_points: int, metric: str) -> dict:
    from sklearn.decomposition import PCA
    from sklearn.manifold import TSNE
    from sklearn.metrics import silhouette_score

    from fdnet.evaluation.plots import evenly_spaced

    names, chosen = [], []
    for condition, v in vectors.items():
        keep = evenly_spaced(len(v), max_points)
        chosen.append(v[keep])
        names += [condition] * len(keep)
    x = np.concatenate(chosen).astype(np.float64)
    labels = np.array(names)
    perplexity = float(min(30, max(2, (len(x) - 1) // 3)))
    # Exact gradients up to a thousand points: here about twice as fast as Barnes-Hut (1.9 vs 3.2 s
    # for 120 points, 16 vs 35 s for 600), and no approximation.
    tsne_method = "exact" if len(x) <= 1000 else "barnes_hut"
    out = {"labels": labels, "full_silhouette": finite_or_none(silhouette_score(x, labels, metric=metric))}
    for method, reducer in (
        ("pca", PCA(n_components=2, random_state=0)),
        (
            "tsne",
            TSNE(
                n_components=2,
                perplexity=perplexity,
                init="pca",
                random_state=0,
                learning_rate="auto",
                method=tsne_method,
            ),
        ),
    ):
        points = reducer.fit_transform(x)
        out[method] = points
        out[f"{method}_silhouette"] = finite_or_none(silhouette_score(points, labels))
    return out


def _places_figure(ctx, handle, path) -> tuple[list, object]:
    """Fig. 12: the appearance vectors of a few places under every condition. The places are
    reference images of the first pair (spread over the traverse); each other condition shows
    them through its pair with that reference condition."""
    from fdnet.evaluation import plots

    anchor = ctx.pairs[0].split.reference
    views = {}  # condition -> (its split against the anchor, anchor index -> query index)
    for pair in ctx.pairs:
        if pair.reference == anchor.name and pair.query not in views:
            found: dict[int, int] = {}
            for q in range(len(pair.split.query)):
                r = matched_reference(pair.split, q)
                if r is not None:
                    found.setdefault(r, q)
            views[pair.query] = (pair.split, found)
    everywhere = [r for r in range(len(anchor)) if all(r in found for _, found in views.values())]
    candidates = everywhere or sorted(set().union(*(found for _, found in views.values())))
    if not candidates:
        return [], None
    picks = [candidates[i] for i in plots.evenly_spaced(len(candidates), PLACES_SHOWN)]
    anchor_vectors = ctx.vectors(handle, anchor.paths, kind="appearance", what=anchor.name)
    plt = plots.pyplot()
    fig, axes = plt.subplots(len(picks), 1, figsize=(9, 2.3 * len(picks)), squeeze=False)
    components = min(PLOTTED_COMPONENTS, anchor_vectors.shape[1])
    places = []
    for row, r in enumerate(picks):
        ax = axes[row, 0]
        lines = [(anchor.name, anchor.paths[r].name, anchor_vectors[r])]
        for condition, (split, found) in views.items():
            if r in found:
                vectors = ctx.vectors(handle, split.query.paths, kind="appearance", what=condition)
                lines.append((condition, split.query.paths[found[r]].name, vectors[found[r]]))
        for condition, name, vector in lines:
            ax.plot(vector[:components], label=f"{condition}: {name}", linewidth=1)
            places.append(
                {
                    "place": f"T{row + 1}",
                    "condition": condition,
                    "image": name,
                    "distance_to_first": float(np.linalg.norm(vector - anchor_vectors[r])),
                }
            )
        ax.set_ylabel(f"T{row + 1}")
        ax.legend(loc="upper right", fontsize="x-small")
    axes[-1, 0].set_xlabel(f"appearance vector component (first {components} of {anchor_vectors.shape[1]})")
    fig.suptitle("Appearance vectors of the same places under each condition", fontsize="medium")
    fig.tight_layout()
    return places, plots.save_figure(fig, path)


def run(ctx) -> dict:
    from fdnet.evaluation import plots

    handle = ctx.handles["fdnet"]
    rng = np.random.default_rng(0)
    plt = plots.pyplot()

    unordered = _unordered_pairs(ctx.pairs)
    differences = [_content_differences(ctx, handle, pair, rng) for pair in unordered]
    drawn = [d for d in differences if "_histograms" in d]
    histogram_figure = None
    if drawn:
        fig, axes = plt.subplots(1, len(drawn), figsize=(5 * len(drawn), 3.6), squeeze=False)
        for ax, d in zip(axes[0], drawn):
            same, other = d.pop("_histograms")
            top = float(np.quantile(np.r_[same, other], 0.995)) or 1.0
            ax.hist(other, bins=60, range=(0, top), density=True, alpha=0.6, label="different places")
            ax.hist(same, bins=60, range=(0, top), density=True, alpha=0.6, label="same place")
            ax.axvline(PAPER_THRESHOLD, color="k", linestyle=":", linewidth=1, label=f"{PAPER_THRESHOLD}")
            ax.set_xlabel("|v_c(x) - v_c(y)| per component")
            ax.set_title(f"{d['query']} vs {d['reference']}", fontsize="medium")
            ax.legend(fontsize="x-small")
        axes[0, 0].set_ylabel("density")
        fig.tight_layout()
        histogram_figure = plots.save_figure(fig, ctx.figure_path("content_differences.png"))

    places, places_figure = _places_figure(ctx, handle, ctx.figure_path("appearance_places.png"))

    traverses = condition_traverses(ctx.pairs)
    content = {c: ctx.vectors(handle, t.paths, what=c) for c, t in traverses.items()}
    appearance = {c: ctx.vectors(handle, t.paths, kind="appearance", what=c) for c, t in traverses.items()}
    ctx.log(f"[{NAME}] PCA and t-SNE of {sum(len(v) for v in content.values())} images' vectors")
    embedded = {
        "appearance": _embeddings(appearance, ctx.settings.embedding_points, "euclidean"),
        "content": _embeddings(content, ctx.settings.embedding_points, "cosine"),
    }
    fig, axes = plt.subplots(2, 2, figsize=(10, 9))
    scores = []
    for row, vector in enumerate(("appearance", "content")):
        e = embedded[vector]
        for col, method in enumerate(("pca", "tsne")):
            ax = axes[row, col]
            for condition in traverses:
                mask = e["labels"] == condition
                ax.scatter(e[method][mask, 0], e[method][mask, 1], s=8, alpha=0.7, label=condition)
            score = e[f"{method}_silhouette"]
            ax.set_title(
                f"{vector} vectors, {'PCA' if method == 'pca' else 't-SNE'}: silhouette {number(score)}",
                fontsize="medium",
            )
            ax.set_xticks([])
            ax.set_yticks([])
            ax.legend(fontsize="x-small", markerscale=2)
            scores.append(
                {
                    "vector": vector,
                    "embedding": method,
                    "silhouette_2d": score,
                    "silhouette_full": e["full_silhouette"],
                    "points": int(len(e["labels"])),
                }
            )
    fig.tight_layout()
    embedding_figure = plots.save_figure(fig, ctx.figure_path("embeddings.png"))
    return {
        "vector_length": int(handle.descriptor.dim),
        "content_differences": differences,
        "histogram_figure": ctx.relative(histogram_figure) if histogram_figure else None,
        "places": places,
        "places_figure": ctx.relative(places_figure) if places_figure else None,
        "embeddings": scores,
        "embedding_figure": ctx.relative(embedding_figure),
        "conditions": list(traverses),
    }


def render(document: dict) -> list:
    return _differences_blocks(document) + _places_blocks(document) + _embedding_blocks(document)


def _differences_blocks(document: dict) -> list:
    """Fig. 11: element-wise content differences per pair, their histograms, and the distances
    between whole content and appearance vectors."""
    blocks: list = [Heading("Content differences, same place vs different places (Fig. 11)")]
    rows = []
    for d in document["content_differences"]:
        if "mean_abs_difference_same_place" not in d:
            rows.append([f"{d['query']} vs {d['reference']}", str(d["num_places"])] + ["-"] * 5)
            continue
        rows.append(
            [
                f"{d['query']} vs {d['reference']}",
                str(d["num_places"]),
                number(d["mean_abs_difference_same_place"], 4),
                number(d["mean_abs_difference_other_place"], 4),
                number(d["share_below_threshold_same_place"]),
                number(d["share_below_threshold_other_place"]),
                number(d["same_place_closer_auc"]),
            ]
        )
    blocks.append(
        Table(
            [
                "conditions",
                "places",
                "mean |dv_c| same place",
                "mean |dv_c| other place",
                f"share < {PAPER_THRESHOLD} same",
                f"share < {PAPER_THRESHOLD} other",
                "P(same place closer)",
            ],
            rows,
            "Element-wise differences of unit content vectors (FDNet's descriptor); P(same place closer) "
            "= how often a same-place pair's mean difference is below a different-place pair's (ROC AUC)",
        )
    )
    if document.get("histogram_figure"):
        blocks.append(
            Figure(
                document["histogram_figure"],
                "Histograms of |v_c(x) - v_c(y)|: same place under two "
                "conditions vs different places (dotted: the paper's 0.05)",
            )
        )
    rows = []
    for d in document["content_differences"]:
        for vector in ("content", "appearance"):
            distances = d.get(f"{vector}_distances")
            if not distances:
                continue
            across, within = distances["same_place_other_condition"], distances["other_place_same_condition"]
            rows.append(
                [
                    f"{d['query']} vs {d['reference']}",
                    vector,
                    number(across),
                    number(within),
                    number(across / within if across is not None and within else None),
                ]
            )
    blocks.append(
        Table(
            ["conditions", "vector", "same place, other condition", "other place, same condition", "ratio"],
            rows,
            "Mean Euclidean distance between whole vectors: content should keep the place (ratio below 1), "
            "appearance the condition (ratio above 1)",
        )
    )
    return blocks


def _places_blocks(document: dict) -> list:
    """Fig. 12: the appearance vectors of the places drawn, with their distances."""
    blocks: list = [Heading("Appearance vectors of a few places (Fig. 12)")]
    if document.get("places_figure"):
        blocks.append(
            Table(
                ["place", "condition", "image", "|v_a - v_a of the first condition|"],
                [[p["place"], p["condition"], p["image"], number(p["distance_to_first"])] for p in document["places"]],
                "The places drawn below: within a place, a distance is the change of condition",
            )
        )
        blocks.append(
            Figure(document["places_figure"], "Appearance vectors v_a of the same places under each condition")
        )
    return blocks


def _embedding_blocks(document: dict) -> list:
    """Fig. 13: the silhouettes by condition of each embedding, and whether appearance separates
    the conditions more than content, as the paper expects."""
    blocks: list = [Heading("2-D embeddings coloured by condition (Fig. 13)")]
    rows = [
        [
            s["vector"],
            "PCA" if s["embedding"] == "pca" else "t-SNE",
            str(s["points"]),
            number(s["silhouette_2d"]),
            number(s["silhouette_full"]),
        ]
        for s in document["embeddings"]
    ]
    blocks.append(
        Table(
            ["vectors", "embedding", "points", "silhouette (2-D)", "silhouette (full vectors)"],
            rows,
            "Silhouette by condition: near 1 = conditions form separate clusters, near 0 or below = mixed",
        )
    )
    full = {s["vector"]: s["silhouette_full"] for s in document["embeddings"]}
    if full.get("appearance") is not None and full.get("content") is not None:
        expected = full["appearance"] > full["content"]
        blocks.append(
            Paragraph(
                f"Appearance vectors separate the conditions {'more' if expected else 'less'} than content vectors "
                f"(silhouette {number(full['appearance'])} vs {number(full['content'])} on the full vectors): "
                + ("as the paper expects." if expected else "not what the paper expects."),
                note=not expected,
            )
        )
    blocks.append(
        Figure(
            document["embedding_figure"],
            "PCA and t-SNE of appearance (top) and content (bottom) " "vectors, coloured by condition",
        )
    )
    return blocks
