"""Experiment ``ablation`` (not in the paper, which motivates each part of FDNet without removing
it): FDNet as a preset trains it, and the same run without each of its three training signals.

Variants (the ablation switches of :class:`fdnet.methods.fdnet.config.LossConfig`):

* ``full`` - the preset as it is;
* ``no-critic`` - ``loss.adversarial=false``: no D_a and no L_e^adv (the critic stage skipped);
* ``no-triplet`` - ``loss.appearance_triplet=false``: no L_a;
* ``no-reconstruction`` - ``loss.reconstruction=false``: no L_r (no decoder).

Per preset (``--ablation-preset``, default ``cpu``; several may be given) the four runs are given
(``--ablation-runs VARIANT=DIR,...``; the preset is the run's own, its switches must be the
variant's) or trained here on ``--ablation-train-frames`` into ``OUT/ablation-runs/<preset>/<variant>/``,
with the schedule :data:`SCHEDULES` states for the preset (the preset's own otherwise) and
``--ablation-set [PRESET:]KEY=VALUE`` on top; a finished run is reused and an interrupted one
resumes. Per preset and pair: R@1, R@100P (raw and fdnet's margin rule), P@maxR and AUC-PR of each
variant, how many queries' top-1 answer changes against the full run (with McNemar's exact test),
and PR curves. With ``--seeds N`` each variant trained here is trained N times (seeds S, S+1, ...;
:mod:`fdnet.reproduce.seeds`) and each number is the mean over its runs, with the spread and each
run's numbers beside.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from fdnet.errors import ConfigError
from fdnet.reproduce.ablation_report import METRICS
from fdnet.reproduce.ablation_report import render as render  # the runner renders each experiment's section
from fdnet.reproduce.sections import finite_or_none

NAME = "ablation"
TITLE = "Ablation: FDNet without its critic, its appearance triplet loss or its reconstruction"
PAPER = "none (the paper motivates L_e^adv, L_a and L_r in section 3 but does not train without them)"
#: it reads only its own FDNet runs: the command's methods (--method, --checkpoint) need not run
COMPARES_METHODS = False

#: variant -> the ablation switches it sets, in report order
VARIANTS = {
    "full": {},
    "no-critic": {"loss.adversarial": False},
    "no-triplet": {"loss.appearance_triplet": False},
    "no-reconstruction": {"loss.reconstruction": False},
}
#: what each variant removes, for the report
REMOVES = {
    "full": "nothing",
    "no-critic": "D_a and L_e^adv (loss.adversarial=false)",
    "no-triplet": "L_a (loss.appearance_triplet=false)",
    "no-reconstruction": "L_r and the decoder (loss.reconstruction=false)",
}
DEFAULT_PRESETS = ("cpu",)
#: the schedule each preset's variants are trained at here (before --ablation-set), where it is not
#: the preset's own: paper-native's whole schedule (73,000 steps, over two hours per run on 2
#: cores) is a tenth here, each stage in the paper's proportion: about 15 minutes per variant
SCHEDULES = {
    "paper-native": {
        "schedule.pretrain_autoencoder_steps": 500,
        "schedule.pretrain_critic_steps": 800,
        "schedule.joint_steps": 6000,
    },
}

#: what a rerun of this experiment alone needs besides the command's flags (the report's hint)
RERUN_FLAGS = (
    "--ablation-train-frames START:END [--ablation-preset cpu,paper-native] "
    "(or --ablation-runs full=DIR,no-critic=DIR,no-triplet=DIR,no-reconstruction=DIR)"
)


def _trains(settings) -> bool:
    return bool(settings.ablation_presets or settings.ablation_train_frames)


def presets(settings) -> list[str]:
    """The presets whose variants are trained here (none when only runs are given)."""
    if not _trains(settings):
        return []
    return list(settings.ablation_presets or DEFAULT_PRESETS)


def unavailable(ctx) -> str | None:
    s = ctx.settings
    if not s.ablation_runs and not _trains(s):
        return (
            "needs FDNet runs of each variant: --ablation-runs full=DIR,no-critic=DIR,no-triplet=DIR,"
            "no-reconstruction=DIR, or --ablation-train-frames START:END (with --ablation-preset, default cpu) "
            "to train them here"
        )
    for variant, folder in s.ablation_runs:
        if variant not in VARIANTS:
            raise ConfigError(f"--ablation-runs {variant}={folder}: unknown variant; choose from {', '.join(VARIANTS)}")
        if not Path(folder).is_dir():
            raise ConfigError(f"--ablation-runs {variant}={folder}: run directory not found")
    if _trains(s):
        from fdnet.methods.fdnet.config import PRESETS

        for name in presets(s):
            if name not in PRESETS:
                raise ConfigError(f"--ablation-preset {name}: unknown FDNet preset; choose from {', '.join(PRESETS)}")
        for scope in s.ablation_overrides:
            if scope and scope not in presets(s):
                raise ConfigError(
                    f"--ablation-set {scope}:...: {scope} is not among the trained presets "
                    f"({', '.join(presets(s))})"
                )
        check_training(s)
        for name in presets(s):
            for variant in VARIANTS:
                training_config(s, name, variant)  # a bad --ablation-set is an error before any work
    return None


def check_training(settings) -> None:
    """Refuse to train (or validate) on the frames the experiments evaluate on."""
    if settings.dataset_format:
        return  # the format's train split (or --ablation-train-frames as its split) is the paper's
    from fdnet.data.dataset import check_training_frames, frame_ranges_overlap

    check_training_frames(
        settings.ablation_train_frames, settings.frames, "--ablation-train-frames", "--ablation-preset"
    )
    for scope, overrides in settings.ablation_overrides.items():
        frames = overrides.get("validation.frames")
        if frames and frame_ranges_overlap(str(frames), settings.frames):
            raise ConfigError(
                f"--ablation-set {scope + ':' if scope else ''}validation.frames={frames} overlaps the "
                f"evaluated frames --frames {settings.frames or 'all'}: validate on other frames"
            )


def overrides_for(settings, preset_name: str) -> dict:
    """The settings the experiment trains ``preset_name``'s variants with, beside the switches:
    :data:`SCHEDULES`, then ``--ablation-set`` for every preset, then for this one."""
    return {
        **SCHEDULES.get(preset_name, {}),
        **settings.ablation_overrides.get("", {}),
        **settings.ablation_overrides.get(preset_name, {}),
    }


def training_config(settings, preset_name: str, variant: str, seed: int | None = None):
    """The run config of one variant on ``settings.data`` (training frames only); ``seed`` replaces
    its ``runtime.seed`` (None: the preset's, or ``--ablation-set runtime.seed=S``)."""
    from fdnet.config import replace_dotted
    from fdnet.methods.fdnet.config import preset, validate

    config = preset(preset_name)
    data = dataclasses.replace(
        config.data,
        root=str(settings.data),
        conditions=tuple(settings.conditions or ()),
        dataset_format=settings.dataset_format or "",
    )
    if settings.dataset_format:
        data = dataclasses.replace(data, split=settings.ablation_train_frames or "")
    else:
        data = dataclasses.replace(data, frames=settings.ablation_train_frames)
    config = dataclasses.replace(config, data=data)
    config = replace_dotted(config, {**overrides_for(settings, preset_name), **VARIANTS[variant]})
    if seed is not None and seed != config.runtime.seed:
        config = replace_dotted(config, {"runtime.seed": seed})
    validate(config)
    return config


def trained_runs(ctx, preset_name: str, variant: str) -> list[Path]:
    """Train (or reuse, or resume) one variant ``--seeds N`` times, seeds S, S+1, ... from its
    config's own S: the first into ``OUT/ablation-runs/<preset>/<variant>/``, seed S+k into
    ``...<variant>-seed<S+k>/`` (see :mod:`fdnet.reproduce.seeds`); returns the run folders."""
    from fdnet.reproduce.seeds import seed_folder, seeds_from

    folder = ctx.out / "ablation-runs" / preset_name / variant
    first = training_config(ctx.settings, preset_name, variant).runtime.seed
    folders = []
    for seed in seeds_from(first, ctx.settings.seeds):
        where = seed_folder(folder, first, seed)
        _train(ctx, preset_name, variant, where, None if seed == first else seed)
        folders.append(where)
    return folders


def _train(ctx, preset_name: str, variant: str, folder: Path, seed: int | None = None) -> None:
    from fdnet import runs

    config = training_config(ctx.settings, preset_name, variant, seed)
    if seed is not None:
        variant = f"{variant} (seed {seed})"  # how the log names this run
    if runs.is_run(folder):
        from fdnet.methods.fdnet.config import FDNetRunConfig

        # the newest checkpoint's step (the descriptor reads best/, which may be an earlier one)
        checkpoint = runs.latest_checkpoint(folder)
        if runs.load_training_state(checkpoint)["step"] >= runs.load_config(checkpoint, FDNetRunConfig).total_steps:
            ctx.log(f"[{NAME}] {preset_name}/{variant}: finished run in {folder}, reused")
            return
    import torch

    from fdnet.methods.fdnet.training import train

    ctx.log(f"[{NAME}] {preset_name}/{variant}: training {config.total_steps} steps into {folder}")
    threads = torch.get_num_threads()
    try:
        train(
            config,
            folder,
            resume=runs.is_run(folder),
            progress=ctx.settings.progress,
            command=ctx.settings.command or "fdnet reproduce",
        )
    finally:
        torch.set_num_threads(threads)  # the preset sets its own; the experiments after keep --threads


def variant_of(config) -> str:
    """The variant a run's ablation switches make (ConfigError for a combination of several)."""
    off = config.ablated()
    for variant, switches in VARIANTS.items():
        if sorted(key.partition(".")[2] for key in switches) == sorted(off):
            return variant
    raise ConfigError(
        f"a run without {' and '.join(off)} is none of this experiment's variants "
        f"({', '.join(VARIANTS)}: one part removed at a time)"
    )


def ablation_runs(ctx) -> dict[str, dict[str, list[Path]]]:
    """preset -> variant -> its run directories: the given run (one; grouped by the preset it was
    trained with) and, for the presets trained here, the variants not given (``--seeds N``: N runs,
    one per seed)."""
    from fdnet.methods.fdnet.config import FDNetRunConfig
    from fdnet.runs import load_config, weights_folder

    s = ctx.settings
    groups: dict[str, dict[str, Path]] = {}
    for variant, folder in s.ablation_runs:
        config = load_config(weights_folder(folder), FDNetRunConfig)
        actual = variant_of(config)
        if actual != variant:
            raise ConfigError(
                f"--ablation-runs {variant}={folder}: that run was trained as {actual} "
                f"({', '.join(f'loss.{n}=false' for n in config.ablated()) or 'every switch on'})"
            )
        group = groups.setdefault(config.preset, {})
        if variant in group:
            raise ConfigError(
                f"--ablation-runs: two {config.preset} runs for {variant} ({group[variant][0]}, " f"{folder})"
            )
        group[variant] = [Path(folder)]
    for name in presets(s):
        group = groups.setdefault(name, {})
        for variant in VARIANTS:
            if variant not in group:
                group[variant] = trained_runs(ctx, name, variant)
    return {name: {v: group[v] for v in VARIANTS if v in group} for name, group in groups.items()}


def _schedule(config) -> dict:
    autoencoder, critic, joint = config.stage_steps
    return {
        "autoencoder": autoencoder,
        "critic": critic,
        "joint": joint,
        "total": config.total_steps,
        "critic_updates_per_step": config.schedule.critic_updates_per_step if config.loss.adversarial else 0,
    }


def weights_stage(schedule: dict, step: int) -> str:
    """The training stage the weights at ``step`` end (a stage's last step belongs to it)."""
    if step <= schedule["autoencoder"]:
        return "auto-encoder"
    if step <= schedule["autoencoder"] + schedule["critic"]:
        return "critic"
    return "joint"


def _differences(full, other) -> list[str]:
    """Settings in which a variant's run differs from the full run's, the switches aside."""
    from fdnet.runs import config_differences

    switches = {f"loss.{name}" for name in ("adversarial", "appearance_triplet", "reconstruction")}
    return [d for d in config_differences(full, other) if d.partition(":")[0] not in switches]


def _mcnemar(right_full, right_variant) -> dict:
    """Queries whose top-1 answer is right in one run and wrong in the other, and McNemar's exact
    two-sided p-value (binomial on the discordant queries)."""
    import numpy as np
    from scipy.stats import binomtest

    only_full = int(np.sum(right_full & ~right_variant))
    only_variant = int(np.sum(right_variant & ~right_full))
    discordant = only_full + only_variant
    p = binomtest(only_full, discordant, 0.5).pvalue if discordant else 1.0
    return {"right_only_in_full": only_full, "right_only_in_variant": only_variant, "p_value": float(p)}


def _compare(ctx, pair, handles: dict) -> tuple[dict, list[dict]]:
    """The results and table rows of one pair for one run per variant (``handles``: variant ->
    handle); each variant but the full one is compared with the full run given beside it."""
    import numpy as np

    from fdnet.decisions.acceptance import DEFAULT_ACCEPTANCE

    results = {v: ctx.result(h, pair.split, pair.slug) for v, h in handles.items()}
    right = {v: r.ground_truth.correct_mask(np.asarray(r.retrieved)[:, :1])[:, 0] for v, r in results.items()}
    queries, _ = ctx.pair_vectors(handles["full"], pair.split) if "full" in handles else (None, None)
    rows_out = []
    for variant, result in results.items():
        metrics = result.metrics[ctx.protocol]
        margin = result.by_acceptance.get(DEFAULT_ACCEPTANCE, {}).get(ctx.protocol)
        row = {
            "variant": variant,
            "recall_at_1": finite_or_none(metrics.recall_at_n[1]),
            "recall_at_100_precision": finite_or_none(metrics.recall_at_100_precision),
            "recall_at_100_precision_margin": finite_or_none(margin.recall_at_100_precision)
            if margin is not None
            else None,
            "precision_at_max_recall": finite_or_none(metrics.precision_at_max_recall),
            "auc_pr": finite_or_none(metrics.auc_pr),
            "pr_curve": metrics.curve.to_dict(),
        }
        if variant != "full" and "full" in results:
            row["against_full"] = _mcnemar(right["full"], right[variant])
            mine, _ = ctx.pair_vectors(handles[variant], pair.split)
            row["same_content_vectors_as_full"] = bool(np.array_equal(mine, queries))
        rows_out.append(row)
    return results, rows_out


def _over_seeds(ctx, pair, seeded: dict, seeds: dict, first_rows: list[dict]) -> None:
    """With ``--seeds N``: each row of a variant with several runs gets ``per_seed`` (each run's
    numbers, its seed, and its comparison with the full run of the same seed index) and ``spread``
    (each number's n, mean, sample standard deviation, min and max); its numbers become the means,
    ``same_content_vectors_as_full`` holds when it holds for every seed, and ``pr_curve`` and
    ``against_full`` stay the first seed's."""
    from fdnet.reproduce.seeds import spread

    longest = max(len(hs) for hs in seeded.values())
    by_seed = [{row["variant"]: row for row in first_rows}]
    for k in range(1, longest):
        handles = {v: hs[k] for v, hs in seeded.items() if len(hs) > k}
        if "full" not in handles and "full" in seeded:
            handles["full"] = seeded["full"][0]  # a given full run (one seed) stands for every seed
        by_seed.append({row["variant"]: row for row in _compare(ctx, pair, handles)[1]})
    for row in first_rows:
        variant = row["variant"]
        if len(seeded[variant]) < 2:
            continue
        runs = [(seeds[variant][k], by_seed[k][variant]) for k in range(len(seeded[variant]))]
        row["per_seed"] = [
            {
                "seed": seed,
                **{key: r[key] for key in METRICS},
                **{key: r[key] for key in ("against_full", "same_content_vectors_as_full") if key in r},
            }
            for seed, r in runs
        ]
        row["spread"] = {key: spread([r[key] for _, r in runs]) for key in METRICS}
        row.update({key: row["spread"][key]["mean"] for key in METRICS})
        if "same_content_vectors_as_full" in row:
            row["same_content_vectors_as_full"] = all(r.get("same_content_vectors_as_full") for _, r in runs)


def run(ctx) -> dict:
    from fdnet.decisions.acceptance import DEFAULT_ACCEPTANCE

    options = {k: v for k, v in ctx.settings.method_options.get("fdnet", {}).items() if k != "checkpoint"}
    groups = [
        _preset_group(ctx, preset_name, variants, options) for preset_name, variants in ablation_runs(ctx).items()
    ]
    document = {
        "variants": list(VARIANTS),
        "removes": REMOVES,
        "acceptance": DEFAULT_ACCEPTANCE,
        "groups": groups,
        "train_frames": ctx.settings.ablation_train_frames,
    }
    if ctx.settings.seeds > 1:
        document["seeds"] = ctx.settings.seeds  # runs per variant trained here (--seeds N)
    return document


def _preset_group(ctx, preset_name: str, variants: dict[str, list[Path]], options: dict) -> dict:
    """One preset's part of the document: its runs, their numbers on every pair (against the full
    run, over the seeds with ``--seeds N``) and the figure of their PR curves."""
    from fdnet.evaluation import plots

    # variant -> one handle per run (per seed); the first seed's has a single run's label
    seeded = {
        variant: [
            ctx.add_method(
                f"fdnet[{preset_name}/{variant if k == 0 else folder.name}]",
                "fdnet",
                {**options, "checkpoint": str(folder)},
                required=True,
                compared=False,
            )
            for k, folder in enumerate(folders)
        ]
        for variant, folders in variants.items()
    }
    handles = {v: hs[0] for v, hs in seeded.items()}
    seeds = {v: [h.descriptor.config.runtime.seed for h in hs] for v, hs in seeded.items()}
    runs_info = _runs_info(variants, seeded)
    pairs = []
    plt = plots.pyplot()
    columns = min(3, len(ctx.pairs))
    rows = -(-len(ctx.pairs) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4.8 * columns, 4.3 * rows), squeeze=False)
    for ax, pair in zip(axes.flat, ctx.pairs):
        results, rows_out = _compare(ctx, pair, handles)
        if any(len(hs) > 1 for hs in seeded.values()):
            _over_seeds(ctx, pair, seeded, seeds, rows_out)
        plots.draw_pr_curves(
            ax, {v: (r.metrics[ctx.protocol].curve, r.metrics[ctx.protocol].auc_pr) for v, r in results.items()}
        )
        ax.set_title(pair.label, fontsize="medium")
        pairs.append(
            {
                "reference": pair.reference,
                "query": pair.query,
                "num_queries": int(pair.split.ground_truth.num_queries),
                "variants": rows_out,
            }
        )
    for ax in list(axes.flat)[len(ctx.pairs) :]:
        ax.axis("off")
    fig.suptitle(f"{preset_name}: PR curves per variant ({ctx.protocol_label})", fontsize="medium")
    fig.tight_layout()
    figure = plots.save_figure(fig, ctx.figure_path(f"pr_{preset_name}.png"))
    group = {
        "preset": preset_name,
        "trained_here": preset_name in presets(ctx.settings),
        "settings": overrides_for(ctx.settings, preset_name) if preset_name in presets(ctx.settings) else {},
        "runs": runs_info,
        "pairs": pairs,
        "figure": ctx.relative(figure),
        "missing": [v for v in VARIANTS if v not in handles],
    }
    if any(len(s) > 1 for s in seeds.values()):
        group["seeds"] = seeds  # variant -> the seeds of its runs, in run order
    return group


def _runs_info(variants: dict[str, list[Path]], seeded: dict) -> list[dict]:
    """What the report says of each run (``seeded``: variant -> its handles, one per folder of
    ``variants``): its seed, schedule, step and stage of its weights, and the settings in which it
    differs from the full run of the same seed index (the one full run when it was given)."""
    full = seeded.get("full")
    runs_info = []
    for v, hs in seeded.items():
        for k, h in enumerate(hs):
            config = h.descriptor.config
            against = full[min(k, len(full) - 1)].descriptor.config if full else None
            schedule = _schedule(config)
            runs_info.append(
                {
                    "variant": v,
                    "removes": REMOVES[v],
                    "run": str(variants[v][k]),
                    "step": h.descriptor.step,
                    "seed": config.runtime.seed,
                    "schedule": schedule,
                    "weights_stage": weights_stage(schedule, h.descriptor.step),
                    "differences_from_full": _differences(against, config)
                    if against is not None and v != "full"
                    else [],
                }
            )
    return runs_info
