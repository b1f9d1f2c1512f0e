"""`fdnet reproduce`: the paper's experiments on a dataset, one self-contained HTML report.

Parses the flags into :class:`fdnet.reproduce.ReproduceSettings` and calls
:func:`fdnet.reproduce.reproduce`; docs/reproduce.md describes the experiments.
"""

from __future__ import annotations

import shlex

from fdnet.cli.common import dataset_format_list, thread_count

EXPERIMENT_NAMES = "comparison, lengths, similarity, disentanglement, viewpoint, runtime, examples"
OPTIONAL_EXPERIMENT_NAMES = "ablation"

# (group, flag, add_argument keywords). One table serves the parser and the command line the
# report records, so the recorded command always has the flags the parser knows.
ARGUMENTS = (
    (
        "data",
        "--data",
        dict(
            required=True,
            metavar="DIR",
            help="dataset folder: one sub-folder per condition, or a published layout with " "--dataset-format",
        ),
    ),
    (
        "data",
        "--dataset-format",
        dict(
            metavar="NAME",
            help=f"read --data in a published layout ({dataset_format_list()}) "
            "with the paper's protocol; see docs/datasets.md",
        ),
    ),
    (
        "data",
        "--conditions",
        dict(
            metavar="A,B,...",
            help="conditions to compare, every ordered pair (default: all sub-folders; with "
            "--dataset-format: the format's default pair)",
        ),
    ),
    (
        "data",
        "--frames",
        dict(metavar="START:END", help="evaluate only these frames of every condition (END exclusive)"),
    ),
    ("data", "--split", dict(help="with --dataset-format: a named split (default: the format's test split)")),
    (
        "data",
        "--tolerance",
        dict(type=int, help="frame tolerance of a correct match (plain folders: default 0; " "formats: the paper's)"),
    ),
    (
        "data",
        "--format-set",
        dict(
            action="append",
            default=[],
            metavar="KEY=VALUE",
            help="with --dataset-format: a protocol setting of the format (repeatable)",
        ),
    ),
    (
        "methods",
        "--checkpoint",
        dict(
            action="append",
            default=[],
            metavar="[METHOD:]RUN_DIR",
            help="the FDNet run (from `fdnet train`), also read by the trunk baseline; "
            "without it FDNet is listed as not run and the baselines still are; "
            "other trained methods as METHOD:RUN_DIR (netvlad:..., calc:...), "
            "repeatable",
        ),
    ),
    (
        "methods",
        "--method",
        dict(
            metavar="LIST",
            help="comma-separated methods (default: fdnet, trunk and every baseline; those "
            "that cannot run here are listed in the report with the reason)",
        ),
    ),
    (
        "methods",
        "--weights",
        dict(
            action="append",
            default=[],
            metavar="[METHOD:]PATH",
            help="weights file a method accepts (conv3 AlexNet, hybridnet, the onnx model), " "repeatable",
        ),
    ),
    (
        "methods",
        "--vectors",
        dict(
            action="append",
            default=[],
            metavar="FILE",
            help="precomputed: vectors computed elsewhere, keyed by image (repeatable)",
        ),
    ),
    (
        "methods",
        "--vocabulary",
        dict(
            action="append",
            default=[],
            metavar="[dbow:]FILE",
            help="DBoW vocabulary (default: learnt from each pair's references)",
        ),
    ),
    (
        "methods",
        "--fit",
        dict(
            action="append",
            default=[],
            metavar="[METHOD:]DIR",
            help="dataset folder the methods that learn from images (dbow, trunk-whitened) learn "
            "from, every condition sub-folder (default: each pair's reference images)",
        ),
    ),
    (
        "methods",
        "--fit-frames",
        dict(
            action="append",
            default=[],
            metavar="[METHOD:]START:END",
            help="with --fit: only these frames of every condition (training frames)",
        ),
    ),
    (
        "methods",
        "--method-set",
        dict(
            action="append",
            default=[],
            metavar="[METHOD:]KEY=VALUE",
            help="a method setting, e.g. conv3:dim=512 (repeatable)",
        ),
    ),
    (
        "experiments",
        "--experiments",
        dict(
            metavar="LIST",
            help=f"experiments to run (default the paper's: {EXPERIMENT_NAMES}); "
            f"{OPTIONAL_EXPERIMENT_NAMES} runs only when named",
        ),
    ),
    (
        "experiments",
        "--length-runs",
        dict(
            metavar="L=DIR,...",
            help="lengths: the FDNet runs per vector length, e.g. "
            "256=runs/L256,512=runs/L512,1024=runs/L1024,2048=runs/L2048",
        ),
    ),
    (
        "experiments",
        "--length-preset",
        dict(
            metavar="PRESET",
            help="lengths: train the runs not given by --length-runs with this "
            "FDNet preset (cpu, paper, paper-native, cpu-scratch, tiny) into "
            "OUT/length-runs/",
        ),
    ),
    (
        "experiments",
        "--length-train-frames",
        dict(
            metavar="START:END",
            help="lengths: frames to train on (plain folders: required, "
            "outside --frames; formats: a split, default train)",
        ),
    ),
    (
        "experiments",
        "--length-set",
        dict(
            action="append",
            default=[],
            metavar="KEY=VALUE",
            help="lengths: a training setting for the trained runs, e.g. " "schedule.joint_steps=500 (repeatable)",
        ),
    ),
    (
        "experiments",
        "--ablation-runs",
        dict(
            metavar="VARIANT=DIR,...",
            help="ablation: FDNet runs of the variants (full, no-critic, no-triplet, "
            "no-reconstruction), grouped by the preset each was trained with, "
            "e.g. full=runs/a,no-critic=runs/a-nc",
        ),
    ),
    (
        "experiments",
        "--ablation-preset",
        dict(
            metavar="LIST",
            help="ablation: FDNet presets whose variants not given by "
            "--ablation-runs are trained into OUT/ablation-runs/ (default cpu), "
            "e.g. cpu,paper-native",
        ),
    ),
    (
        "experiments",
        "--ablation-train-frames",
        dict(
            metavar="START:END",
            help="ablation: frames to train the variants on (plain folders: "
            "required to train, outside --frames; formats: a split, "
            "default train)",
        ),
    ),
    (
        "experiments",
        "--ablation-set",
        dict(
            action="append",
            default=[],
            metavar="[PRESET:]KEY=VALUE",
            help="ablation: a training setting of the trained variants, for every "
            "preset or one, e.g. paper-native:schedule.joint_steps=60000 "
            "(repeatable)",
        ),
    ),
    (
        "experiments",
        "--seeds",
        dict(
            type=int,
            default=1,
            metavar="N",
            help="lengths and ablation: train each run trained here N times, seeds S, "
            "S+1, ... (S its runtime.seed), and report each number's mean, sample "
            "standard deviation and min-max over the N runs (default 1)",
        ),
    ),
    (
        "experiments",
        "--viewpoint-pair",
        dict(metavar="REFERENCE,QUERY", help="viewpoint: the pair to crop (default: the first pair)"),
    ),
    (
        "experiments",
        "--overlaps",
        dict(default="100,90,75,65", metavar="LIST", help="viewpoint: overlaps in percent (default 100,90,75,65)"),
    ),
    ("experiments", "--examples", dict(type=int, default=5, help="examples: queries per pair (default 5)")),
    (
        "experiments",
        "--runtime-images",
        dict(type=int, default=32, help="runtime and lengths: images timed per method (default 32)"),
    ),
    (
        "experiments",
        "--embedding-points",
        dict(
            type=int,
            default=300,
            help="disentanglement: at most this many images per condition in " "the PCA/t-SNE embeddings (default 300)",
        ),
    ),
    (
        "output",
        "--out",
        dict(
            required=True,
            metavar="OUT_DIR",
            help="folder for report.html, one JSON per experiment, figures/ and cache/",
        ),
    ),
    ("output", "--batch-size", dict(type=int, default=32, help="images described per batch (default 32)")),
    (
        "output",
        "--cache",
        dict(
            metavar="DIR",
            help="where described vectors are cached (default "
            "$FDNET_CACHE/reproduce/descriptors, else "
            "~/.cache/fdnet/reproduce/descriptors)",
        ),
    ),
    (
        "output",
        "--protocol",
        dict(
            default="recall-over-queries",
            choices=("recall-over-queries", "vprbench"),
            help="how PR numbers are computed: the paper's (recall over queries, 500 "
            "thresholds; default) or VPR-Bench's (every top-1 score)",
        ),
    ),
    (
        "output",
        "--threads",
        dict(
            type=thread_count(),
            help="CPU threads for torch, BLAS and scikit-learn "
            "(default: all cores; on a shared machine 1 keeps "
            "timings meaningful)",
        ),
    ),
    (
        "output",
        "--device",
        dict(
            default="auto",
            metavar="auto|cpu|cuda|cuda:N",
            help="where the torch methods (fdnet, trunk, conv3, netvlad, calc, hybridnet) run "
            "(default auto: a GPU when there is one); the others run on the CPU",
        ),
    ),
    ("output", "--no-progress", dict(action="store_true", help="no progress bars")),
)


def register(sub) -> None:
    p = sub.add_parser(
        "reproduce",
        help="run the paper's experiments and write one self-contained HTML report",
        description="Run the paper's experiments ("
        + EXPERIMENT_NAMES
        + "; "
        + OPTIONAL_EXPERIMENT_NAMES
        + " when named) on a dataset and write "
        "OUT_DIR/report.html (figures embedded, opens offline), one JSON of numbers per experiment "
        "and the figures. Descriptors are cached in OUT_DIR/cache: rerun one experiment with "
        "--experiments NAME, add a method, or resume an interrupted run at little cost.",
    )
    groups = {name: p.add_argument_group(name) for name in ("data", "methods", "experiments", "output")}
    for group, flag, keywords in ARGUMENTS:
        groups[group].add_argument(flag, **keywords)
    p.set_defaults(func=run)


def command_line(args) -> str:
    """The command as the parser understood it, flags in the parser's order."""
    parts = ["fdnet", "reproduce"]
    for _, flag, keywords in ARGUMENTS:
        value = getattr(args, flag[2:].replace("-", "_"))
        if keywords.get("action") == "store_true":
            parts += [flag] if value else []
        elif keywords.get("action") == "append":
            for item in value or []:
                parts += [flag, str(item)]
        elif value is not None and value != keywords.get("default"):
            parts += [flag, str(value)]
    return shlex.join(parts)


def _names(text: str | None) -> list[str] | None:
    return None if text is None else [n.strip() for n in text.split(",") if n.strip()]


def _length_runs(text: str | None) -> dict:
    from pathlib import Path

    from fdnet.errors import ConfigError

    runs = {}
    for item in _names(text) or []:
        length, sep, folder = item.partition("=")
        if not sep or not length.strip().isdigit() or not folder.strip():
            raise ConfigError(f"--length-runs {item!r}: expected L=RUN_DIR, e.g. 512=runs/L512")
        runs[int(length)] = Path(folder.strip())
    return runs


def _ablation_runs(text: str | None) -> list:
    from pathlib import Path

    from fdnet.errors import ConfigError

    runs = []
    for item in _names(text) or []:
        variant, sep, folder = item.partition("=")
        if not sep or not variant.strip() or not folder.strip():
            raise ConfigError(f"--ablation-runs {item!r}: expected VARIANT=RUN_DIR, e.g. no-critic=runs/a-nc")
        runs.append((variant.strip(), Path(folder.strip())))
    return runs


def _ablation_overrides(items: list[str]) -> dict:
    """``[PRESET:]KEY=VALUE`` items -> {"": every preset's, PRESET: that preset's} settings."""
    from fdnet.config import parse_overrides

    out: dict = {}
    for item in items:
        key, sep, value = item.partition("=")
        scope, colon, name = key.partition(":")
        scope, name = (scope.strip(), name) if colon else ("", key)
        out.setdefault(scope, {}).update(parse_overrides([f"{name}{sep}{value}"]))
    return out


def _overlaps(text: str) -> tuple[float, ...]:
    from fdnet.errors import ConfigError

    values = []
    for item in _names(text) or []:
        try:
            value = float(item)
        except ValueError as exc:
            raise ConfigError(f"--overlaps {text!r}: {item!r} is not a number (percent, e.g. 100,90,75,65)") from exc
        values.append(value / 100.0 if value > 1.0 else value)
    if not values:
        raise ConfigError("--overlaps is empty")
    return tuple(values)


def _warn_unused_experiment_flags(args) -> None:
    """A flag of an experiment this run leaves out does nothing: say so (a warning, not a refusal:
    rerunning a command with ``--experiments NAME`` keeps its other flags). Each flag's help names
    its experiments before the colon."""
    import logging
    import re

    from fdnet.reproduce.sections import EXPERIMENTS

    chosen = set(_names(args.experiments) or EXPERIMENTS)
    for group, flag, keywords in ARGUMENTS:
        value = getattr(args, flag.lstrip("-").replace("-", "_"), None)
        if group != "experiments" or flag == "--experiments" or value in (None, [], keywords.get("default")):
            continue  # --experiments chooses the experiments: it is never one's own flag
        owners = re.split(r", | and ", keywords["help"].partition(":")[0])
        if not chosen & set(owners):
            logging.getLogger(__name__).warning(
                f"{flag} is for the {' and '.join(owners)} experiment{'s' if len(owners) > 1 else ''}, which this run "
                "leaves out (--experiments): it does nothing here"
            )


def run(args) -> int:
    import argparse
    from pathlib import Path

    from fdnet.backbones import check_device_spec
    from fdnet.cli.common import method_options, set_threads, split_scope
    from fdnet.config import parse_overrides
    from fdnet.descriptors.registry import available_methods
    from fdnet.errors import ConfigError
    from fdnet.reproduce import DEFAULT_METHODS, ReproduceSettings, reproduce

    check_device_spec(args.device, where="--device")  # before any work
    known = available_methods()
    scoped = [(split_scope(c, known), c) for c in args.checkpoint]
    fdnet_runs = [run for (label, run), _ in scoped if label in (None, "fdnet")]
    other_runs = [c for (label, _), c in scoped if label not in (None, "fdnet")]
    if len(fdnet_runs) > 1:
        raise ConfigError(
            "--checkpoint: give the FDNet run directory exactly once (RUN_DIR or fdnet:RUN_DIR); "
            "other trained methods as METHOD:RUN_DIR"
        )
    from fdnet.runs import is_run

    if fdnet_runs and not is_run(fdnet_runs[0]):  # refused before any work, not written into the report
        raise ConfigError(
            f"--checkpoint {fdnet_runs[0]}: not a run directory with a complete checkpoint "
            "(make one with `fdnet train`)"
        )
    for flag, text in (("--experiments", args.experiments), ("--method", args.method)):
        if text is not None and not _names(text):
            raise ConfigError(
                f"{flag} {text!r}: names no {flag.lstrip('-').rstrip('s')}; leave the flag out for " "the default"
            )
    _warn_unused_experiment_flags(args)
    methods = _names(args.method)
    considered = methods or list(DEFAULT_METHODS)
    others = argparse.Namespace(
        method=",".join(considered),
        weights=args.weights,
        vocabulary=args.vocabulary,
        vectors=args.vectors,
        fit=args.fit,
        fit_frames=args.fit_frames,
        method_set=args.method_set,
        checkpoint=other_runs,
    )
    options = {name: {**method_options(others, name), "device": args.device} for name in considered if name in known}
    viewpoint = _names(args.viewpoint_pair)
    if viewpoint is not None and len(viewpoint) != 2:
        raise ConfigError(f"--viewpoint-pair {args.viewpoint_pair!r}: expected REFERENCE,QUERY")
    settings = ReproduceSettings(
        data=Path(args.data),
        out=Path(args.out),
        checkpoint=Path(fdnet_runs[0]) if fdnet_runs else None,
        cache=Path(args.cache) if args.cache else None,
        dataset_format=args.dataset_format,
        conditions=_names(args.conditions),
        frames=args.frames,
        split=args.split,
        tolerance=args.tolerance,
        format_options=parse_overrides(args.format_set),
        methods=methods,
        method_options=options,
        experiments=_names(args.experiments),
        length_runs=_length_runs(args.length_runs),
        length_preset=args.length_preset,
        length_train_frames=args.length_train_frames,
        length_overrides=parse_overrides(args.length_set),
        ablation_runs=_ablation_runs(args.ablation_runs),
        ablation_presets=_names(args.ablation_preset),
        ablation_train_frames=args.ablation_train_frames,
        ablation_overrides=_ablation_overrides(args.ablation_set),
        seeds=args.seeds,
        viewpoint_pair=tuple(viewpoint) if viewpoint else None,
        overlaps=_overlaps(args.overlaps),
        examples=args.examples,
        runtime_images=args.runtime_images,
        embedding_points=args.embedding_points,
        batch_size=args.batch_size,
        threads=args.threads,
        progress=not args.no_progress,
        protocol=args.protocol,
        command=command_line(args),
    )
    set_threads(args.threads)
    report = reproduce(settings)
    print(f"fdnet reproduce: report in {report}")
    return 0
