"""`fdnet train [METHOD]`: train a method into a run directory (FDNet when no method is named).

Every trained method of the method registry (:mod:`fdnet.descriptors.registry`) trains through
this one command, with the same flags, the same preset mechanism (``--preset`` names one of the
method's presets; ``--config`` and ``--set`` change any setting on top) and the same shared loop
(:mod:`fdnet.training.loop`: time budget, Ctrl-C, crash-safe checkpoints, exact resume,
validation with ``best/``, ``log.csv``, device, precision and threads from ``runtime.*``).

FDNet is unsupervised with respect to place: it needs only which condition each image belongs to
(its folder). CALC learns without labels too; NetVLAD learns from the frame-aligned ground truth
between conditions (positives within ``--tolerance`` frames).

``torchrun --nproc-per-node N -m fdnet train ...`` trains data-parallel on N processes (see
:mod:`fdnet.training.distributed`): rank 0 builds the settings (it alone reads ``--config`` files
and, on ``--resume``, the run's own settings) and broadcasts them, and it alone prints.
"""

from __future__ import annotations

import argparse

from fdnet.cli.common import add_training_arguments

DEFAULT_METHOD = "fdnet"


def add_arguments(parser: argparse.ArgumentParser, methods: list[str], default: str) -> None:
    """The method argument and every training flag, with choices and help from the registry."""
    from fdnet.descriptors.registry import spec

    parser.add_argument(
        "method",
        choices=methods,
        nargs="?",
        default=default,
        metavar="METHOD",
        help=f"the method to train: {', '.join(methods)} (default {default})",
    )
    add_training_arguments(parser, data_required=False)
    presets = list(dict.fromkeys(p for m in methods for p in spec(m).presets))
    per_method = "; ".join(f"{m}: {'|'.join(spec(m).presets)} (default {spec(m).default_preset})" for m in methods)
    # checked in build_config, not by argparse, so a wrong one is the usual one-line error naming the method's
    parser.add_argument(
        "--preset",
        default=None,
        metavar="|".join(presets),
        help=f"the settings to start from ({per_method}); with --resume, the run's own",
    )
    parser.add_argument(
        "--tolerance",
        type=int,
        help="ground-truth tolerance in frames of the methods that learn from it (data.tolerance; "
        "NetVLAD's positives, default 0)",
    )


def register(sub) -> None:
    from fdnet.descriptors.registry import trained_methods

    methods = trained_methods()
    p = sub.add_parser(
        "train",
        help=f"train a method into a run directory ({', '.join(methods)}; default " f"{DEFAULT_METHOD})",
        description="Train FDNet (staged: auto-encoder, discriminator, joint adversarial; no place "
        "labels) or another trained method (`fdnet methods` lists them). Writes RUN_DIR/{config.yaml, "
        "checkpoints/, log.csv, best/}; see docs/runs.md. Settings: the --preset, then --config, then "
        "the flags, then --set (the same paths for every method: optim.*, runtime.*, data.*, "
        "validation.*; docs/methods.md).",
    )
    add_arguments(p, methods, DEFAULT_METHOD)
    p.set_defaults(func=run)


def build_config(args):
    """Preset (or, with --resume, the run's own settings) <- --config <- flags <- --set."""
    from fdnet.cli.common import apply_training_arguments, check_resume_target
    from fdnet.descriptors.registry import spec
    from fdnet.errors import ConfigError

    method = spec(args.method)
    check_resume_target(args)
    if args.preset and args.preset not in method.presets:
        method.preset(args.preset)  # the error naming the method's presets
    if args.resume:
        config = load_run_config(method, args.out)
        saved = getattr(config, "preset", "")
        if args.preset and args.preset != saved:
            raise ConfigError(
                f"{args.out}: was trained with preset {saved or 'unrecorded'!r}, not {args.preset!r} "
                "(--resume keeps the run's own settings; change them with --set and --override)"
            )
    else:
        if args.data is None:
            raise ConfigError("--data is required (it may be left out only with --resume)")
        config = method.preset(args.preset)
    return apply_training_arguments(config, args)


def load_run_config(method, run_dir):
    """The settings of the run in ``run_dir``, checked to be a run of ``method``."""
    from fdnet import runs
    from fdnet.methods import load_method_config

    cls = method.config_class()
    if "method" in getattr(cls, "__dataclass_fields__", {}):
        return load_method_config(run_dir, cls, method.name)
    from fdnet.config import read_yaml_file
    from fdnet.errors import ConfigError

    path = runs.latest_checkpoint(run_dir) / runs.CONFIG_FILE
    saved = (read_yaml_file(path) or {}).get("method") if path.is_file() else None
    if saved:  # a baseline's run: its config names its method
        raise ConfigError(
            f"{path}: is a {saved} run, not a {method.name} run; resume it with `fdnet train {saved} "
            f"--out {run_dir} --resume`"
        )
    return runs.load_config(run_dir, cls)


def run(args) -> int:
    from fdnet.training.distributed import run_with_settings_from_rank_0

    return run_with_settings_from_rank_0(lambda: build_config(args), lambda config: _train(args, config))


def _train(args, config) -> int:
    import time

    from fdnet.descriptors.registry import spec

    started = time.monotonic()
    train = spec(args.method).train_function()
    try:
        summary = train(
            config,
            args.out,
            resume=args.resume,
            override=args.override,
            max_minutes=args.max_minutes,
            progress=not args.no_progress,
            command=getattr(args, "command_line", f"fdnet train {args.method}"),
        )
    except KeyboardInterrupt:
        from fdnet import runs

        # Ctrl-C while images are read (or trunk blocks scored) comes before any checkpoint
        if runs.is_run(args.out):
            print(f"fdnet train: interrupted; the newest checkpoint is in {args.out} (continue with --resume)")
        else:
            print(
                f"fdnet train: interrupted before the first checkpoint; nothing was saved in {args.out} "
                "(run the same command again to start)"
            )
        raise
    if summary["changes"]:
        print(
            f"fdnet train: resumed with changed settings (recorded in {args.out}/changes.yaml): "
            + "; ".join(summary["changes"])
        )
    line = (
        f"fdnet train: {summary['status']} at step {summary['step']}/{summary['total_steps']} "
        # the loop's minutes, and the command's (reading images and choosing a start included)
        f"after {summary['elapsed_seconds'] / 60:.1f} min of training "
        f"({(time.monotonic() - started) / 60:.1f} min in all)"
        + (f" on {summary['world_size']} processes" if summary["world_size"] > 1 else "")
        + f"; run in {summary['run_dir']}"
    )
    if summary["best_step"] >= 0:
        line += f"; best validation R@1 {summary['best_recall@1']:.3f} at step {summary['best_step']} (in best/)"
    if summary["best_step"] >= 0:
        line += f"; use it with --method {args.method} --checkpoint {args.out} (which means best/)"
    else:
        line += f"; use it with --method {args.method} --checkpoint {args.out}"
    print(line)
    if summary["status"] == "time limit":
        print("fdnet train: continue with --resume to finish the schedule")
    return 0
