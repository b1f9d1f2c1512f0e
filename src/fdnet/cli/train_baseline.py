"""`fdnet train-baseline {calc,netvlad}`: train one of the paper's learned baselines.

CALC learns without labels from every image of the chosen conditions; NetVLAD learns from the
frame-aligned ground truth between conditions (positives within ``--tolerance`` frames). Both
run on the same training loop as FDNet (time budget, Ctrl-C, crash-safe checkpoints, exact
resume, validation with best/, log.csv) and write a run directory for
``fdnet evaluate --method calc|netvlad --checkpoint RUN_DIR``. Under ``torchrun`` they train
data-parallel like ``fdnet train`` (see :mod:`fdnet.training.distributed`).
"""

from __future__ import annotations

from fdnet.cli.common import add_training_arguments

METHODS = ("calc", "netvlad")


def register(sub) -> None:
    p = sub.add_parser(
        "train-baseline",
        help="train a learned baseline (CALC or NetVLAD) into a run directory",
        description="Train CALC (unsupervised HOG auto-encoder) or NetVLAD (triplet loss on the "
                    "training split's frame-aligned ground truth) and save a run directory usable "
                    "with --checkpoint.",
    )
    p.add_argument("method", choices=METHODS, help="which baseline to train")
    add_training_arguments(p, data_required=False)
    p.add_argument("--tolerance", type=int,
                   help="ground-truth tolerance in frames (NetVLAD's positives; default 0)")
    p.add_argument("--steps", type=int, help="number of training steps (default: the preset's)")
    p.add_argument("--preset", choices=("default", "small", "tiny"), default=None,
                   help="default: the method's standard setting (CALC: the original network); "
                        "small: CALC at half resolution and width (CALC only); tiny: a seconds-long "
                        "run for tests")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads (default: torch's own choice)")
    p.set_defaults(func=run)


def build_config(args):
    """The run config from the preset (or the run being resumed), the data flags and --set."""
    import dataclasses

    from fdnet.cli.common import apply_training_arguments, check_resume_target
    from fdnet.config import replace_dotted
    from fdnet.errors import ConfigError
    from fdnet.methods import method_module

    config_module = method_module(args.method, "config")
    check_resume_target(args)
    if args.resume:
        config = config_module.load_run_config(args.out)
        if args.preset:
            raise ConfigError("--preset does not apply with --resume (the run keeps its own settings)")
    else:
        preset = args.preset or "default"
        if preset not in config_module.PRESETS:
            raise ConfigError(f"--preset {preset}: {args.method} has presets {', '.join(config_module.PRESETS)}")
        config = config_module.PRESETS[preset]()
    if args.tolerance is not None:
        if not hasattr(config.data, "tolerance"):
            raise ConfigError(f"--tolerance: {args.method} learns without place labels and takes no tolerance")
        config = dataclasses.replace(config, data=dataclasses.replace(config.data, tolerance=int(args.tolerance)))
    if args.steps is not None:
        config = replace_dotted(config, {"train.steps": int(args.steps)})
    return apply_training_arguments(config, args)


def run(args) -> int:
    import torch

    from fdnet.training.distributed import run_with_settings_from_rank_0

    if args.threads is not None:
        torch.set_num_threads(max(1, args.threads))
    return run_with_settings_from_rank_0(lambda: build_config(args), lambda config: _train(args, config))


def _train(args, config) -> int:
    from fdnet.methods import method_module

    summary = method_module(args.method, "training").train(
        config, args.out, resume=args.resume, override=args.override, max_minutes=args.max_minutes,
        progress=not args.no_progress,
        command=getattr(args, "command_line", f"fdnet train-baseline {args.method}"))
    if summary["changes"]:
        print(f"{args.method}: resumed with changed settings (recorded in {args.out}/changes.yaml): "
              + "; ".join(summary["changes"]))
    processes = f" on {summary['world_size']} processes" if summary["world_size"] > 1 else ""
    print(f"{args.method}: {summary['status']} at step {summary['step']}/{summary['total_steps']} after "
          f"{summary['elapsed_seconds']:.0f} s{processes}; use it with --method {args.method} --checkpoint {args.out}")
    return 0
