"""Experiment ``comparison`` (paper Tables 3 and 4, Figs 7 and 14-17): every method on every
ordered pair of conditions under the paper's protocol (500 uniform thresholds, recall over queries).

Per pair: R@100P and P@maxR (the paper's two columns), R@1/5/10 and AUC-PR for FDNet, the trunk
alone and every baseline, the best of each column marked, and the paper's own numbers beside ours
when the paper reports the same dataset pair; one figure of all methods' PR curves. The paper's
columns threshold the best-match similarity (acceptance rule ``raw``); beside its R@100P stands
R@100P under fdnet's default acceptance rule (``margin``, :mod:`fdnet.decisions.acceptance`).
"""

from __future__ import annotations

from fdnet.reproduce.sections import Figure, Heading, Paragraph, Table, best_cells, number, pair_name

NAME = "comparison"
TITLE = "Method comparison over every ordered pair of conditions"
PAPER = "Tables 3 and 4 (recall at 100% precision, precision at maximum recall); Figs 7, 14-17 (PR curves)"

#: (column title, key of the result JSON); recall_at_n keys are "1", "5", "10"
COLUMNS = (
    ("R@100P", "recall_at_100_precision"),
    ("P@maxR", "precision_at_max_recall"),
    ("R@1", "1"),
    ("R@5", "5"),
    ("R@10", "10"),
    ("AUC-PR", "auc_pr"),
)


def _columns(rule: str | None) -> tuple:
    """COLUMNS with R@100P under ``rule`` right after the paper's (raw) R@100P."""
    if not rule or rule == "raw":
        return COLUMNS
    return COLUMNS[:1] + ((f"R@100P {rule}", f"accept:{rule}"),) + COLUMNS[1:]


def unavailable(ctx) -> str | None:
    return None


def run(ctx) -> dict:
    from fdnet.decisions.acceptance import DEFAULT_ACCEPTANCE
    from fdnet.evaluation import plots
    from fdnet.evaluation.report import format_table
    from fdnet.paper import paper_pair

    pairs = []
    for pair in ctx.pairs:
        results = [ctx.result(handle, pair.split, pair.slug) for handle in ctx.available()]
        ctx.log(f"[{NAME}] {pair.label}\n" + format_table(results, ctx.protocol))
        plt = plots.pyplot()
        fig, ax = plt.subplots(figsize=(7.5, 4.5))
        plots.draw_pr_curves(
            ax, {r.method: (r.metrics[ctx.protocol].curve, r.metrics[ctx.protocol].auc_pr) for r in results}
        )
        # beside the axes: with a dozen methods a legend inside covers the low-precision curves
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small")
        ax.set_title(f"{pair.label} ({ctx.protocol_label})", fontsize="medium")
        figure = plots.save_figure(fig, ctx.figure_path(f"pr_{pair.slug}.png"))
        paper = paper_pair(ctx.dataset, pair.reference, pair.query)
        gt = pair.split.ground_truth
        pairs.append(
            {
                "reference": pair.reference,
                "query": pair.query,
                "description": pair.split.description,
                "ground_truth": gt.description,
                "num_queries": gt.num_queries,
                "num_queries_with_match": int(gt.has_match.sum()),
                "num_references": gt.num_references,
                "results": [r.to_dict(ctx.protocol) for r in results],
                "paper_source": paper[0] if paper else None,
                "paper": paper[1] if paper else None,
                "figure": ctx.relative(figure),
            }
        )
    return {"pairs": pairs, "skipped": ctx.skipped(), "paper_dataset": ctx.dataset, "acceptance": DEFAULT_ACCEPTANCE}


def _value(result: dict, key: str):
    if key.startswith("accept:"):
        per = result.get("per_acceptance", {}).get(key.partition(":")[2])
        return None if per is None else per.get("recall_at_100_precision")
    return result["recall_at_n"].get(key) if key.isdigit() else result.get(key)


def _rank(rows: list[list], column: int, method: str) -> str:
    values = sorted({row[column] for row in rows if row[column] is not None}, reverse=True)
    mine = next((row[column] for row in rows if row[0] == method), None)
    if mine is None:
        return "-"
    return f"{values.index(mine) + 1} of {len(rows)}"


def render(document: dict) -> list:
    blocks: list = [
        Paragraph(
            "Each query's best match is accepted when its score passes a threshold; 500 thresholds "
            "uniform over the min-max-normalised best-match scores give the PR curve (paper 5.1.2). "
            "R@100P = largest recall at precision 1; P@maxR = precision at the largest recall; "
            "R@N = queries with a true match among their N best; AUC-PR = area under the PR curve. "
            "Bold with a star: the best of our methods in that column."
            + (
                f" R@100P {document['acceptance']}: the same, accepting each query by fdnet's "
                f"{document['acceptance']} acceptance score instead of its best-match similarity (docs/decisions.md)."
                if document.get("acceptance") not in (None, "raw")
                else ""
            )
        )
    ]
    columns = _columns(document.get("acceptance"))
    titles = [title for title, _ in columns]
    if not document.get("paper_dataset"):
        blocks.append(
            Paragraph(
                "The paper reports no results on this dataset, so no paper numbers are shown "
                "(it has Nordland in Table 3; Alderley, Oxford RobotCar, St Lucia and FAS in Table 4).",
                note=True,
            )
        )
    for skipped in document.get("skipped", []):
        blocks.append(Paragraph(f"{skipped['method']}: not run here ({skipped['reason']})", note=True))
    for pair in document["pairs"]:
        blocks.append(
            Heading(
                f"{pair_name(pair['query'], pair['reference'])} (query \u2192 reference): "
                f"{pair['num_queries']} queries ({pair['num_queries_with_match']} with a true match) "
                f"x {pair['num_references']} references; {pair['ground_truth']}"
            )
        )
        paper = pair.get("paper") or {}
        rows = [[r["method"]] + [_value(r, key) for _, key in columns] for r in pair["results"]]
        marked = best_cells(rows, list(range(1, len(columns) + 1)))
        header = ["method"] + titles
        if paper:
            header += ["paper R@100P", "paper P@maxR"]
        cells = []
        for row in rows:
            line = [row[0]] + [number(v) for v in row[1:]]
            if paper:
                theirs = paper.get(row[0])
                line += (
                    [number(theirs["recall_at_100_precision"]), number(theirs["precision_at_max_recall"])]
                    if theirs
                    else ["-", "-"]
                )
            cells.append(line)
        ours = {row[0] for row in rows}
        for method, theirs in paper.items():
            if method not in ours:
                cells.append(
                    [f"{method} ({theirs['paper_name']}, paper only)"]
                    + ["-"] * len(columns)
                    + [number(theirs["recall_at_100_precision"]), number(theirs["precision_at_max_recall"])]
                )
        caption = f"{pair_name(pair['query'], pair['reference'])}"
        if paper:
            caption += (
                f"; paper columns: {pair['paper_source']}, the paper's own numbers (its query/reference "
                f"direction is not stated, so they stand beside both directions). What differs: the "
                f"paper trained at 224x224 on its own frames and tested on its own split of the full "
                f"dataset; ours are {pair.get('description') or 'these frames'}, at the run's input size, "
                f"under {pair['ground_truth']}; its R@100P and P@maxR are those of the raw best-match score "
                f"over 500 thresholds (ours in the columns marked raw), so compare the orders of the methods "
                f"more than the values"
            )
        blocks.append(Table(header, cells, caption, marked))
        if "fdnet" in ours:
            r1, r100p = titles.index("R@1") + 1, titles.index("R@100P") + 1
            blocks.append(
                Paragraph(
                    f"FDNet ranks {_rank(rows, r1, 'fdnet')} by R@1 and {_rank(rows, r100p, 'fdnet')} "
                    f"by R@100P on this pair."
                )
            )
        blocks.append(
            Figure(pair["figure"], f"PR curves, {pair_name(pair['query'], pair['reference'])} " f"(legend: AUC-PR)")
        )
    return blocks
