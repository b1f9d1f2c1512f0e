"""`fdnet train`: train FDNet on a folder of conditions (one sub-folder per condition).

FDNet is unsupervised with respect to place: it needs only which condition each image belongs
to (its folder), never which images show the same place.

``torchrun --nproc-per-node N -m fdnet train ...`` trains data-parallel on N processes (see
:mod:`fdnet.training.distributed`): rank 0 builds the settings (it alone reads ``--config`` files
and, on ``--resume``, the run's own settings) and broadcasts them, and it alone prints.
"""

from __future__ import annotations

from fdnet.cli.common import add_training_arguments


def register(sub) -> None:
    p = sub.add_parser("train", help="train FDNet on multi-condition image folders (no place labels)",
                       description="Train FDNet (staged: auto-encoder, discriminator, joint adversarial). "
                       "Writes RUN_DIR/{config.yaml, checkpoints/, log.csv, best/}; see docs/runs.md.")
    add_training_arguments(p)
    p.add_argument("--preset", default=None,
                   help="paper | cpu | cpu-scratch | tiny (default cpu; with --resume, the run's own)")
    p.set_defaults(func=run)


def build_config(args):
    """Preset (or, with --resume, the run's own settings) <- --config <- flags <- --set."""
    from fdnet import runs
    from fdnet.cli.common import apply_training_arguments, check_resume_target
    from fdnet.errors import ConfigError
    from fdnet.methods.fdnet.config import TrainConfig, preset

    check_resume_target(args)
    if args.resume:
        config = runs.load_config(args.out, TrainConfig)
        if args.preset and args.preset != config.preset:
            raise ConfigError(f"{args.out}: was trained with preset {config.preset!r}, not {args.preset!r}")
    else:
        config = preset(args.preset or "cpu")
    return apply_training_arguments(config, args)


def run(args) -> int:
    from fdnet.training.distributed import run_with_settings_from_rank_0

    return run_with_settings_from_rank_0(lambda: build_config(args), lambda config: _train(args, config))


def _train(args, config) -> int:
    from fdnet.methods.fdnet.training import train

    try:
        summary = train(config, args.out, resume=args.resume, override=args.override,
                        max_minutes=args.max_minutes, progress=not args.no_progress,
                        command=getattr(args, "command_line", "fdnet train"))
    except KeyboardInterrupt:
        from fdnet import runs

        # Ctrl-C while images are read (or trunk blocks scored) comes before any checkpoint
        if runs.is_run(args.out):
            print(f"fdnet train: interrupted; the newest checkpoint is in {args.out} (continue with --resume)")
        else:
            print(f"fdnet train: interrupted before the first checkpoint; nothing was saved in {args.out} "
                  "(run the same command again to start)")
        raise
    if summary["changes"]:
        print(f"fdnet train: resumed with changed settings (recorded in {args.out}/changes.yaml): "
              + "; ".join(summary["changes"]))
    line = (f"fdnet train: {summary['status']} at step {summary['step']}/{summary['total_steps']} "
            f"after {summary['elapsed_seconds'] / 60:.1f} min"
            + (f" on {summary['world_size']} processes" if summary["world_size"] > 1 else "")
            + f"; run in {summary['run_dir']}")
    if summary["best_step"] >= 0:
        line += f"; best validation R@1 {summary['best_recall@1']:.3f} at step {summary['best_step']} (in best/)"
    print(line)
    if summary["status"] == "time limit":
        print("fdnet train: continue with --resume to finish the schedule")
    return 0
