"""Experiment ``examples`` (paper Fig. 9): per pair, a grid of a few queries (evenly spaced over
the traverse) by methods, each cell the method's best match framed green (correct) or red (wrong).
The table lists the same matches as text."""

from __future__ import annotations

from fdnet.reproduce.sections import Figure, Heading, Paragraph, Table, pair_name

NAME = "examples"
TITLE = "Example matches"
PAPER = "Fig. 9 (matched and mismatched images by method; green frame = correct, red = wrong)"


def unavailable(ctx) -> str | None:
    return None


def run(ctx) -> dict:
    from fdnet.evaluation import plots

    pairs = []
    for pair in ctx.pairs:
        split = pair.split
        chosen = plots.evenly_spaced(len(split.query), ctx.settings.examples)
        matches, rows = {}, []
        for handle in ctx.available():
            result = ctx.result(handle, split, pair.slug)
            best = result.retrieved[:, 0]
            correct = split.ground_truth.correct_mask(best[:, None])[:, 0]
            matches[handle.label] = (best, correct)
            rows.append(
                {
                    "method": handle.label,
                    "best": [int(best[q]) for q in chosen],
                    "best_names": [split.reference.paths[best[q]].name for q in chosen],
                    "correct": [bool(correct[q]) for q in chosen],
                }
            )
        figure = plots.plot_match_grid(
            split.query.paths,
            split.reference.paths,
            matches,
            ctx.figure_path(f"examples_{pair.slug}.jpg"),
            count=ctx.settings.examples,
            title=f"{pair.label}: query (top row), then each method's best match",
        )
        pairs.append(
            {
                "reference": pair.reference,
                "query": pair.query,
                "queries": [int(q) for q in chosen],
                "query_names": [split.query.paths[q].name for q in chosen],
                "methods": rows,
                "figure": ctx.relative(figure),
            }
        )
    return {"pairs": pairs}


def render(document: dict) -> list:
    blocks: list = [
        Paragraph(
            "Each column is a query; each row below it a method's best match, framed green "
            "when it is a true match and red when not."
        )
    ]
    for pair in document["pairs"]:
        blocks.append(Heading(f"{pair_name(pair['query'], pair['reference'])}"))
        header = ["method"] + [f"query {q} ({name})" for q, name in zip(pair["queries"], pair["query_names"])]
        rows = [
            [m["method"]]
            + [f"{name} ({'correct' if ok else 'wrong'})" for name, ok in zip(m["best_names"], m["correct"])]
            for m in pair["methods"]
        ]
        rows.append(
            ["correct, of these queries"]
            + [
                f"{sum(m['correct'][i] for m in pair['methods'])} of {len(pair['methods'])} methods"
                for i in range(len(pair["queries"]))
            ]
        )
        name = pair_name(pair["query"], pair["reference"])
        blocks.append(Table(header, rows, f"Best match per query and method, {name}"))
        blocks.append(Figure(pair["figure"], f"Example matches, {pair_name(pair['query'], pair['reference'])}"))
    return blocks
