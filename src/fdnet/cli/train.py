"""`fdnet train`: train FDNet on a folder of conditions (one sub-folder per condition).

FDNet is unsupervised with respect to place: it needs only which condition each image belongs
to (its folder), never which images show the same place.
"""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("train", help="train FDNet on multi-condition image folders (no place labels)",
                       description="Train FDNet (staged: auto-encoder, discriminator, joint adversarial). "
                       "Writes RUN_DIR/{config.yaml, model.safetensors, training_state.pt, log.csv, best/}.")
    p.add_argument("--data", required=True, help="dataset folder with one sub-folder per condition")
    p.add_argument("--out", required=True, help="run directory to write (or to continue with --resume)")
    p.add_argument("--preset", default=None, help="paper | cpu | cpu-scratch | tiny (default cpu; with --resume, the run's own)")
    p.add_argument("--conditions", help="comma-separated conditions to train on (default: all sub-folders)")
    p.add_argument("--frames", help="START:END slice of every condition to train on (END exclusive)")
    p.add_argument("--dataset-format", help="read --data in a published layout (nordland, alderley, oxford_robotcar, "
                   "st_lucia, fas, vprbench, vpr_tutorial, vg_benchmark, folders, or auto); see docs/datasets.md")
    p.add_argument("--split", help="with --dataset-format: a named split (default: the format's train split) or START:END")
    p.add_argument("--config", help="YAML file of settings applied on top of the preset")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one setting, e.g. --set schedule.joint_steps=3000 (repeatable)")
    p.add_argument("--max-minutes", type=float, help="stop cleanly (with a checkpoint) after M minutes")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--validate-reference", help="condition used as reference for periodic validation")
    p.add_argument("--validate-query", help="condition used as query for periodic validation")
    p.add_argument("--validate-frames", help="START:END frames for validation (keep them out of your test split)")
    p.add_argument("--validate-tolerance", type=int, help="frame tolerance of a correct validation match")
    p.add_argument("--validate-every", type=int, help="validate every N steps")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def build_config(args):
    """Preset <- --config YAML <- --set overrides <- explicit flags; or the run's own on --resume."""
    from pathlib import Path

    from fdnet.config import parse_overrides, replace_dotted
    from fdnet.errors import ConfigError
    from fdnet.training.checkpoint import CONFIG_FILE, load_config
    from fdnet.training.config import TrainConfig, apply_yaml, preset

    out = Path(args.out)
    if args.resume:
        if not (out / CONFIG_FILE).exists():
            raise ConfigError(f"{out}: no run to resume (no {CONFIG_FILE}); drop --resume to start one")
        config = load_config(out, TrainConfig)
        if args.preset and args.preset != config.preset:
            raise ConfigError(f"{out}: was trained with preset {config.preset!r}, not {args.preset!r}")
    else:
        config = preset(args.preset or "cpu")
    if args.config:
        config = apply_yaml(config, args.config)
    flags = {"data.root": str(args.data)}
    if args.conditions:
        flags["data.conditions"] = [c.strip() for c in args.conditions.split(",") if c.strip()]
    if args.frames is not None:
        flags["data.frames"] = args.frames
    if args.dataset_format is not None:
        flags["data.dataset_format"] = args.dataset_format
    if args.split is not None:
        flags["data.split"] = args.split
    for flag, key in (("validate_reference", "validation.reference"), ("validate_query", "validation.query"),
                      ("validate_frames", "validation.frames"), ("validate_tolerance", "validation.tolerance"),
                      ("validate_every", "validation.every")):
        if getattr(args, flag) is not None:
            flags[key] = getattr(args, flag)
    config = replace_dotted(config, flags)
    return replace_dotted(config, parse_overrides(args.set))


def run(args) -> int:
    from fdnet.training.config import validate
    from fdnet.training.trainer import Trainer, load_training_images, load_validation_images

    config = build_config(args)
    validate(config)  # settings errors before any image is read
    if config.runtime.threads > 0:
        import torch

        torch.set_num_threads(config.runtime.threads)
    if config.data.dataset_format:
        from fdnet.data.formats import open_training
        from fdnet.errors import ConfigError
        from fdnet.training.trainer import route_training_images

        if config.data.frames:
            raise ConfigError("with --dataset-format, choose frames with --split (a name or START:END), not --frames")
        fmt = config.data.dataset_format
        route = open_training(args.data, None if fmt == "auto" else fmt, config.data.split or None,
                              list(config.data.conditions) or None)
        data = route_training_images(route, config.model.input_size, config.data.batch_per_domain,
                                     config.data.split)
    else:
        data = load_training_images(args.data, config.data.conditions, config.data.frames,
                                    config.model.input_size, config.data.batch_per_domain)
    validation = load_validation_images(args.data, config)
    print(f"fdnet train: preset {config.preset}, conditions {', '.join(data.names)} "
          f"({', '.join(str(len(x)) for x in data.images)} images), input {tuple(config.model.input_size)}, "
          f"{config.total_steps} steps -> {args.out}")
    trainer = Trainer(config, data, args.out, validation=validation, resume=args.resume)
    try:
        summary = trainer.fit(max_minutes=args.max_minutes, progress=not args.no_progress)
    except KeyboardInterrupt:
        print(f"fdnet train: interrupted at step {trainer.step}; checkpoint saved in {args.out} (continue with --resume)")
        raise
    line = (f"fdnet train: {summary['status']} at step {summary['step']}/{summary['total_steps']} "
            f"after {summary['elapsed_seconds'] / 60:.1f} min; run in {summary['run_dir']}")
    if summary["best_step"] >= 0:
        line += f"; best validation R@1 {summary['best_recall@1']:.3f} at step {summary['best_step']} (in best/)"
    print(line)
    if summary["status"] == "time limit":
        print("fdnet train: continue with --resume to finish the schedule")
    return 0
