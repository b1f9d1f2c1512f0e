"""Experiment ``lengths`` (paper Fig. 6, Table 2): FDNet with content vectors of length
L = 256, 512, 1024 and 2048.

The four FDNet runs are given (``length_runs``: L -> run directory), or trained here with a preset
(``length_preset``, on ``length_train_frames`` of the data, ``model.vector_length`` = L, further
settings from ``length_overrides``) into ``OUT/length-runs/L<L>/``; an interrupted training resumes
from its last checkpoint on the next run, and a finished one is reused. Per length: PR curves on
every pair (Fig. 6), R@100P and R@1, extraction ms/image and matching ms/query on this machine
beside the paper's Table 2. With ``--seeds N`` each length trained here is trained N times (seeds S,
S+1, ...; :mod:`fdnet.reproduce.seeds`): its accuracy numbers are the means over the runs, with the
spread and each run's numbers beside; curves and timings are the first seed's run.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from fdnet.errors import ConfigError
from fdnet.reproduce.sections import Figure, Paragraph, Table, best_cells, number, pair_name

NAME = "lengths"
TITLE = "Vector length L = 256, 512, 1024, 2048"
PAPER = "Fig. 6 (PR curves per vector length, Nordland), Table 2 (extraction and matching time per length)"

LENGTHS = (256, 512, 1024, 2048)


#: what a rerun of this experiment alone needs besides the command's flags (the report's hint)
RERUN_FLAGS = "--length-preset cpu --length-train-frames START:END (or --length-runs 256=DIR,512=DIR,1024=DIR,2048=DIR)"


def unavailable(ctx) -> str | None:
    s = ctx.settings
    if not s.length_runs and not s.length_preset:
        return (
            "needs four FDNet runs: --length-runs 256=DIR,512=DIR,1024=DIR,2048=DIR, or --length-preset PRESET "
            "(with --length-train-frames START:END) to train them here"
        )
    if s.length_preset:
        check_training(s)  # training on the evaluated frames is an error before any work
    for length, folder in s.length_runs.items():
        if not Path(folder).is_dir():
            raise ConfigError(f"--length-runs {length}={folder}: run directory not found")
    return None


def training_config(settings, length: int, seed: int | None = None):
    """The preset's run config for FDNet_L on ``settings.data`` (training frames only); ``seed``
    replaces its ``runtime.seed`` (None: the preset's, or ``--length-set runtime.seed=S``)."""
    from fdnet.config import replace_dotted
    from fdnet.methods.fdnet.config import preset

    config = preset(settings.length_preset)
    data = dataclasses.replace(
        config.data,
        root=str(settings.data),
        conditions=tuple(settings.conditions or ()),
        dataset_format=settings.dataset_format or "",
    )
    if settings.dataset_format:
        data = dataclasses.replace(data, split=settings.length_train_frames or "")
    else:
        data = dataclasses.replace(data, frames=settings.length_train_frames)
    config = dataclasses.replace(config, data=data)
    config = replace_dotted(config, {"model.vector_length": length, **settings.length_overrides})
    if seed is not None and seed != config.runtime.seed:
        config = replace_dotted(config, {"runtime.seed": seed})
    return config


def check_training(settings) -> None:
    """Refuse to train on the frames the experiments evaluate on."""
    if settings.dataset_format:
        return  # the format's train split (or --length-train-frames as its split) is the paper's
    from fdnet.data.dataset import check_training_frames

    check_training_frames(settings.length_train_frames, settings.frames, "--length-train-frames", "--length-preset")


def _train(ctx, length: int, folder: Path, seed: int | None = None) -> None:
    from fdnet import runs

    which = f"L = {length}" + (f" (seed {seed})" if seed is not None else "")
    if runs.is_run(folder):
        existing = ctx.factory("fdnet", checkpoint=str(folder))
        if existing.step is not None and existing.step >= existing.config.total_steps:
            ctx.log(f"[{NAME}] {which}: finished run in {folder}, reused")
            return
    import torch

    from fdnet.methods.fdnet.training import train

    ctx.log(f"[{NAME}] {which}: training with preset {ctx.settings.length_preset} into {folder}")
    threads = torch.get_num_threads()
    try:
        train(
            training_config(ctx.settings, length, seed),
            folder,
            resume=runs.is_run(folder),
            progress=ctx.settings.progress,
            command=ctx.settings.command or "fdnet reproduce",
        )
    finally:
        torch.set_num_threads(threads)  # the preset sets its own; the experiments after keep --threads


def length_runs(ctx) -> dict[int, list[Path]]:
    """L -> its run directories: the given run (one), and with ``--length-preset`` the lengths not
    given, trained ``--seeds N`` times (seeds S, S+1, ... from the config's own S; the first into
    ``OUT/length-runs/L<L>/``, seed S+k into ``...L<L>-seed<S+k>/``)."""
    from fdnet.reproduce.seeds import seed_folder, seeds_from

    s = ctx.settings
    chosen = {int(k): [Path(v)] for k, v in s.length_runs.items()}
    if s.length_preset:
        for length in LENGTHS:
            if length not in chosen:
                folder = ctx.out / "length-runs" / f"L{length}"
                first = training_config(s, length).runtime.seed
                chosen[length] = []
                for seed in seeds_from(first, s.seeds):
                    where = seed_folder(folder, first, seed)
                    _train(ctx, length, where, None if seed == first else seed)
                    chosen[length].append(where)
    return dict(sorted(chosen.items()))


#: the accuracy numbers of a length on a pair, averaged over its seeds with --seeds N
METRICS = ("recall_at_100_precision", "precision_at_max_recall", "recall_at_1", "auc_pr")


def _over_seeds(ctx, pair, handles: list, entry: dict) -> None:
    """With ``--seeds N``: ``entry`` (the first seed's numbers) gets ``per_seed`` (each run's seed
    and numbers) and ``spread`` (each number's n, mean, sample standard deviation, min and max),
    and its numbers become the means."""
    from fdnet.reproduce.seeds import spread

    per_seed = []
    for handle in handles:
        metrics = ctx.result(handle, pair.split, pair.slug).metrics[ctx.protocol]
        per_seed.append(
            {
                "seed": handle.descriptor.config.runtime.seed,
                "recall_at_100_precision": metrics.recall_at_100_precision,
                "precision_at_max_recall": metrics.precision_at_max_recall,
                "recall_at_1": metrics.recall_at_n[1],
                "auc_pr": metrics.auc_pr,
            }
        )
    entry["per_seed"] = per_seed
    entry["spread"] = {key: spread([r[key] for r in per_seed]) for key in METRICS}
    entry.update({key: entry["spread"][key]["mean"] for key in METRICS})


def run(ctx) -> dict:
    from fdnet.data.images import load_images
    from fdnet.evaluation import plots
    from fdnet.paper import PAPER_TABLE2
    from fdnet.performance.timing import descriptor_extraction
    from fdnet.reproduce.table5_runtime import ranking_ms_per_query

    options = {k: v for k, v in ctx.settings.method_options.get("fdnet", {}).items() if k != "checkpoint"}
    seeded = {}  # L -> one handle per run (per seed); the first seed's has a single run's label
    for length, folders in length_runs(ctx).items():
        seeded[length] = []
        for k, folder in enumerate(folders):
            handle = ctx.add_method(
                f"fdnet_L{length}" if k == 0 else f"fdnet_{folder.name}",
                "fdnet",
                {**options, "checkpoint": str(folder)},
                required=True,
                compared=False,
            )
            if handle.descriptor.dim != length:
                raise ConfigError(
                    f"{folder}: was given as the L = {length} run but its content vector has "
                    f"length {handle.descriptor.dim}"
                )
            seeded[length].append(handle)
    handles = {length: hs[0] for length, hs in seeded.items()}

    plt = plots.pyplot()
    columns = min(3, len(ctx.pairs))
    rows = -(-len(ctx.pairs) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4.8 * columns, 4.3 * rows), squeeze=False)
    accuracy = []
    for ax, pair in zip(axes.flat, ctx.pairs):
        curves = {}
        for length, handle in handles.items():
            metrics = ctx.result(handle, pair.split, pair.slug).metrics[ctx.protocol]
            curves[f"L = {length}"] = (metrics.curve, metrics.auc_pr)
            accuracy.append(
                {
                    "length": length,
                    "reference": pair.reference,
                    "query": pair.query,
                    "recall_at_100_precision": metrics.recall_at_100_precision,
                    "precision_at_max_recall": metrics.precision_at_max_recall,
                    "recall_at_1": metrics.recall_at_n[1],
                    "auc_pr": metrics.auc_pr,
                }
            )
            if len(seeded[length]) > 1:
                _over_seeds(ctx, pair, seeded[length], accuracy[-1])
        plots.draw_pr_curves(ax, curves)
        ax.set_title(pair.label, fontsize="medium")
    for ax in list(axes.flat)[len(ctx.pairs) :]:
        ax.axis("off")
    fig.tight_layout()
    figure = plots.save_figure(fig, ctx.figure_path("pr_lengths.png"))

    first = ctx.pairs[0].split
    paths = first.query.paths[: ctx.settings.runtime_images]
    timing = []
    for length, handle in handles.items():
        descriptor = handle.descriptor
        images = load_images(paths, descriptor.input_size)
        queries, references = ctx.pair_vectors(handle, first)
        ctx.limit_threads()
        paper = PAPER_TABLE2.get(length, (None, None))
        timing.append(
            {
                "length": length,
                "run": str(handle.options["checkpoint"]),
                "step": descriptor.step,
                "preset": descriptor.config.preset,
                "ms_per_image": descriptor_extraction(descriptor, images, repeats=3),
                "ms_per_query": ranking_ms_per_query(descriptor, queries, references),
                "paper_ms_per_image": paper[0],
                "paper_ms_per_query": paper[1],
            }
        )
    document = {
        "lengths": list(handles),
        "accuracy": accuracy,
        "timing": timing,
        "figure": ctx.relative(figure),
        "pairs": [{"reference": p.reference, "query": p.query} for p in ctx.pairs],
        "num_images_timed": len(paths),
        "map_size": len(first.reference),
        "missing": [length for length in LENGTHS if length not in handles],
    }
    if any(len(hs) > 1 for hs in seeded.values()):
        document["seeds"] = ctx.settings.seeds  # runs per length trained here (--seeds N)
        #: L (as text: a JSON key) -> the seeds of its runs, in run order
        document["run_seeds"] = {
            str(length): [h.descriptor.config.runtime.seed for h in hs] for length, hs in seeded.items()
        }
    return document


def render(document: dict) -> list:
    blocks: list = []
    if document.get("missing"):
        blocks.append(Paragraph(f"No run given for L = {', '.join(map(str, document['missing']))}.", note=True))
    from fdnet.reproduce.seeds import spread_text

    pairs = document["pairs"]
    by_key = {(a["length"], a["reference"], a["query"]): a for a in document["accuracy"]}
    seeds = document.get("seeds")
    if seeds:
        blocks.append(
            Paragraph(
                f"Each length trained here is trained {seeds} times (--seeds {seeds}), with seeds S, S+1, ... from "
                "its run's own S: each accuracy number is the mean over its runs, shown as mean \u00b1 sample "
                "standard deviation (min\u2013max over the runs), each run's own numbers follow; a length given by "
                "--length-runs is one run. The PR curves and the timings are the first seed's runs (the seed does "
                "not change the network's size)."
            )
        )
    for key, title in (("recall_at_100_precision", "R@100P"), ("recall_at_1", "R@1")):
        entries = [[by_key[(length, p["reference"], p["query"])] for p in pairs] for length in document["lengths"]]
        rows = [[f"FDNet_{length}"] + [e[key] for e in row] for length, row in zip(document["lengths"], entries)]
        marked = best_cells(rows, list(range(1, len(pairs) + 1)))
        blocks.append(
            Table(
                ["vector length"] + [f"{pair_name(p['query'], p['reference'])}" for p in pairs],
                [
                    [r[0]] + [spread_text(e["spread"][key]) if e.get("spread") else number(e[key]) for e in row]
                    for r, row in zip(rows, entries)
                ],
                f"{title} per vector length and pair (paper protocol)"
                + (f"; mean \u00b1 sample standard deviation (min\u2013max) over {seeds} seeds" if seeds else ""),
                marked,
            )
        )
    per_seed = [
        [
            f"FDNet_{a['length']}",
            pair_name(a["query"], a["reference"]),
            str(r["seed"]),
            number(r["recall_at_100_precision"]),
            number(r["recall_at_1"]),
            number(r["auc_pr"]),
        ]
        for a in document["accuracy"]
        for r in a.get("per_seed") or []
    ]
    if per_seed:
        blocks.append(
            Table(
                ["vector length", "pair", "seed", "R@100P", "R@1", "AUC-PR"],
                per_seed,
                "each seed's run per vector length and pair",
            )
        )
    rows = [
        [
            f"FDNet_{t['length']}",
            f"{t['preset']} (step {t['step']})",
            number(t["ms_per_image"], 2),
            number(t["paper_ms_per_image"], 1),
            number(t["paper_ms_per_image"] / t["ms_per_image"] if t["paper_ms_per_image"] else None, 2),
            number(t["ms_per_query"], 4),
            number(t["paper_ms_per_query"], 2),
            number(t["paper_ms_per_query"] / t["ms_per_query"] if t["paper_ms_per_query"] else None, 2),
        ]
        for t in document["timing"]
    ]
    blocks.append(
        Table(
            [
                "vector length",
                "run",
                "ms/image",
                "paper ms/image (TITAN X)",
                "paper / ours",
                "ms/query",
                "paper ms/query",
                "paper / ours",
            ],
            rows,
            f"Extraction over {document['num_images_timed']} decoded images and matching against "
            f"{document['map_size']} references on this machine (see the runtime section for the "
            f"hardware); the paper's Table 2 beside, ratio above 1 = faster here",
        )
    )
    blocks.append(
        Figure(
            document["figure"],
            "PR curves per vector length, one panel per pair (Fig. 6)"
            + ("; the first seed's run of each length" if seeds else ""),
        )
    )
    return blocks
