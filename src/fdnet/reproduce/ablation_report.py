"""The report section of experiment ``ablation`` (:mod:`fdnet.reproduce.ablation`), from its JSON
alone: per preset the runs and how they were trained, a table of the variants per pair (each
seed's runs beside when there are several), what removing each part did in words, and the PR
curves.
"""

from __future__ import annotations

from fdnet.reproduce.sections import Figure, Heading, Paragraph, Table, best_cells, number, pair_name

#: the numbers of a variant on a pair (the report's columns), averaged over its seeds with --seeds N
METRICS = (
    "recall_at_1",
    "recall_at_100_precision",
    "recall_at_100_precision_margin",
    "precision_at_max_recall",
    "auc_pr",
)


def _schedule_text(schedule: dict) -> str:
    return (
        f"{schedule['autoencoder']} auto-encoder + {schedule['critic']} critic + {schedule['joint']} joint steps "
        f"({schedule['critic_updates_per_step']} critic updates per joint step)"
    )


#: how a finding names each variant
WITHOUT = {
    "no-critic": "Without the critic (no D_a, no L_e^adv)",
    "no-triplet": "Without the triplet loss L_a",
    "no-reconstruction": "Without reconstruction (no L_r, no decoder)",
}


def _against(name: str, value, reference) -> str:
    if value is None or reference is None:
        return f"{name} {number(value)} (full run {number(reference)})"
    if value == reference:
        return f"{name} {number(value)}, the same as the full run"
    return f"{name} {number(value)} against the full run's {number(reference)} ({value - reference:+.3f})"


def _finding_over_seeds(variant: str, row: dict, full: dict) -> str:
    """What removing the part did on this pair over the runs of several seeds (--seeds N): the
    change of each mean against the spread of both, and McNemar's test per seed."""
    from fdnet.reproduce.seeds import spread_text

    parts = []
    for name, key in (("R@1", "recall_at_1"), ("AUC-PR", "auc_pr"), ("R@100P", "recall_at_100_precision")):
        mine, theirs = row["spread"][key], (full.get("spread") or {}).get(key) or {"mean": full[key]}
        change = (
            f" ({mine['mean'] - theirs['mean']:+.3f})"
            if mine["mean"] is not None and theirs["mean"] is not None
            else ""
        )
        parts.append(f"{name} {spread_text(mine)} against the full run's {spread_text(theirs)}{change}")
    text = (
        f"{WITHOUT[variant]}, mean ± sample standard deviation (min–max) over {len(row['per_seed'])} "
        "seeds: " + "; ".join(parts)
    )
    if row.get("same_content_vectors_as_full"):
        return text + (
            ". For every seed its content vectors are exactly the full run's: in this preset the part "
            "it removes does not reach the content encoder."
        )
    tests = [r["against_full"] for r in row["per_seed"] if r.get("against_full")]
    if not tests:
        return text + "."
    below = sum(t["p_value"] < 0.05 for t in tests)
    values = ", ".join(f"{t['p_value']:.3g}" for t in tests)
    return text + (
        f". McNemar's exact test on the evaluated queries, run against run of the same seed index: p "
        f"below 0.05 for {below} of {len(tests)} pairs of runs (p = {values}): it tests the queries of "
        "one pair of runs, where the spread above is over the runs."
    )


def _finding(variant: str, row: dict, full: dict | None, pair: dict) -> str:
    """What removing the part did on this pair, from the numbers alone."""
    if full is None:
        return ""
    if row.get("per_seed"):
        return _finding_over_seeds(variant, row, full)
    text = f"{WITHOUT[variant]}: " + "; ".join(
        _against(name, row[key], full[key])
        for name, key in (("R@1", "recall_at_1"), ("AUC-PR", "auc_pr"), ("R@100P", "recall_at_100_precision"))
    )
    if row.get("same_content_vectors_as_full"):
        return text + (
            ". Its content vectors are exactly the full run's: in this preset the part it removes does "
            "not reach the content encoder."
        )
    against = row.get("against_full")
    if not against:
        return text + "."
    a, b = against["right_only_in_full"], against["right_only_in_variant"]
    if a + b == 0:
        return text + ". Every query's top-1 answer is right or wrong in both runs alike."
    text += (
        f". The top-1 answer is right only in the full run for {a} of {pair['num_queries']} queries and only "
        f"in this variant for {b} (McNemar's exact p = {against['p_value']:.3g}"
    )
    if against["p_value"] >= 0.05:
        return text + ": these queries alone cannot tell the difference from chance at the 5% level)."
    return text + ": more than chance on these queries at the 5% level, for this one pair of runs)."


def _variation_text(document: dict) -> str:
    """What the section says about run-to-run variation: not measured with one seed, else how."""
    if not document.get("seeds"):
        return (
            "Every variant is one training run with one seed: the differences include run-to-run variation, "
            "which this experiment does not measure; McNemar's test below counts only the evaluated queries, "
            "not that variation."
        )
    return (
        f"Every variant trained here is trained {document['seeds']} times (--seeds {document['seeds']}), with "
        "seeds S, S+1, ... from its run's own S: each number in the tables is the mean over its runs, shown as "
        "mean ± sample standard deviation (min–max over the runs), and each run's own numbers follow "
        "in a table per pair; a variant given by --ablation-runs is one run. The PR curves are the first "
        "seed's runs; McNemar's test counts the evaluated queries of one pair of runs at a time, not the "
        "run-to-run variation."
    )


def _number_or_spread(row: dict, key: str) -> str:
    from fdnet.reproduce.seeds import spread_text

    return spread_text(row["spread"][key]) if row.get("spread") else number(row[key])


def _per_seed_table(group: dict, pair: dict, acceptance: str) -> Table | None:
    """Each run's numbers on one pair, a row per (variant, seed), when a variant has several."""
    rows = [
        [v["variant"], str(r["seed"])] + [number(r[k]) for k in METRICS]
        for v in pair["variants"]
        for r in v.get("per_seed") or []
    ]
    if not rows:
        return None
    return Table(
        ["variant", "seed", "R@1", "R@100P raw", f"R@100P {acceptance}", "P@maxR", "AUC-PR"],
        rows,
        f"{group['preset']}, {pair_name(pair['query'], pair['reference'])}: each seed's run",
    )


def render(document: dict) -> list:
    acceptance = document.get("acceptance", "margin")
    blocks: list = [
        Paragraph(
            "Each variant is the same training as the full run with one part removed (the switch stops it "
            "being computed, not only weighted: fdnet's docs/runs.md says what each switch removes in each preset). "
            f"R@100P raw thresholds the best-match similarity (paper 5.1.2); R@100P {acceptance} accepts each query "
            f"by fdnet's {acceptance} score instead. " + _variation_text(document)
        )
    ]
    for group in document["groups"]:
        blocks += _runs_blocks(group)
        for pair in group["pairs"]:
            blocks += _pair_blocks(group, pair, acceptance)
        blocks.append(
            Figure(
                group["figure"],
                f"{group['preset']}: PR curves of the variants, one panel per pair "
                "(legend: AUC-PR)" + ("; the first seed's run of each variant" if group.get("seeds") else ""),
            )
        )
    return blocks


def _runs_blocks(group: dict) -> list:
    """A preset's heading, what sets its runs apart (missing variants, weights from before the joint
    stage, settings beyond the switch) and the table of its runs."""
    runs = {r["variant"]: r for r in group["runs"]}
    full_run = runs.get("full")
    schedule = _schedule_text(full_run["schedule"]) if full_run else ""
    where = (
        "trained here"
        + (
            f" with {', '.join(f'{k}={v}' for k, v in group['settings'].items())}"
            if group["settings"]
            else " with the preset's own settings"
        )
        if group["trained_here"]
        else "given runs"
    )
    blocks: list = [Heading(f"preset {group['preset']}: {where}; the full run: {schedule}")]
    if group.get("missing"):
        blocks.append(Paragraph(f"No {group['preset']} run for {', '.join(group['missing'])}.", note=True))
    for run in group["runs"]:
        if run.get("weights_stage", "joint") != "joint":
            # best/ by validation can predate the joint stage (e.g. an encoder that the variant's
            # joint training made worse): its numbers are then not those of the trained variant
            blocks.append(
                Paragraph(
                    f"{run['variant']}'s weights (its best by validation) are from step {run['step']}, in its "
                    f"{run['weights_stage']} stage, before any joint step: its numbers below are those of its "
                    "weights before the joint training, which its validation scored lower.",
                    note=True,
                )
            )
        if run["differences_from_full"]:
            blocks.append(
                Paragraph(
                    f"{run['variant']} differs from the full run in more than its switch: "
                    + "; ".join(run["differences_from_full"]),
                    note=True,
                )
            )
    seeded = bool(group.get("seeds"))  # a column for the seed when a variant has several runs
    blocks.append(
        Table(
            ["variant"]
            + ["seed"] * seeded
            + ["removes", "steps (auto-encoder + critic + joint)", "weights at step", "run"],
            [
                [r["variant"]]
                + [str(r.get("seed"))] * seeded
                + [
                    r["removes"],
                    f"{r['schedule']['autoencoder']} + {r['schedule']['critic']} + " f"{r['schedule']['joint']}",
                    f"{r['step']} ({r.get('weights_stage', 'joint')})",
                    r["run"],
                ]
                for r in group["runs"]
            ],
            f"{group['preset']}: the runs",
        )
    )
    return blocks


def _pair_blocks(group: dict, pair: dict, acceptance: str) -> list:
    """A preset's variants on one pair: their table (means over the seeds when there are several),
    each seed's runs, and what removing each part did."""
    rows = [[v["variant"]] + [v[k] for k in METRICS] for v in pair["variants"]]
    marked = best_cells(rows, list(range(1, len(METRICS) + 1)))
    counts = sorted({len(v["per_seed"]) for v in pair["variants"] if v.get("per_seed")})
    over = (
        f"; mean ± sample standard deviation (min–max) over {' or '.join(map(str, counts))} " "seeds" if counts else ""
    )
    blocks: list = [
        Table(
            ["variant", "R@1", "R@100P raw", f"R@100P {acceptance}", "P@maxR", "AUC-PR"],
            [[v["variant"]] + [_number_or_spread(v, k) for k in METRICS] for v in pair["variants"]],
            f"{group['preset']}, {pair_name(pair['query'], pair['reference'])}: "
            f"{pair['num_queries']} queries{over}",
            marked,
        )
    ]
    per_seed = _per_seed_table(group, pair, acceptance)
    if per_seed is not None:
        blocks.append(per_seed)
    full = next((v for v in pair["variants"] if v["variant"] == "full"), None)
    for row in pair["variants"]:
        if row["variant"] != "full":
            sentence = _finding(row["variant"], row, full, pair)
            if sentence:
                blocks.append(Paragraph(sentence))
    return blocks
