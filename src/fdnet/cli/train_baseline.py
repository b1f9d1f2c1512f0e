"""`fdnet train-baseline {calc,netvlad}`: train one of the paper's learned baselines.

CALC learns without labels from every image of the chosen conditions; NetVLAD learns from the
frame-aligned ground truth between conditions (positives within ``--tolerance`` frames). Both
write a run directory for ``fdnet evaluate --method calc|netvlad --checkpoint RUN_DIR``.
"""

from __future__ import annotations

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
    p.add_argument("--data", help="dataset folder with one sub-folder per condition "
                                  "(optional with --resume: the run's own is used)")
    p.add_argument("--out", required=True, help="run directory to write (or to continue with --resume)")
    p.add_argument("--conditions", help="comma-separated condition sub-folders to train on (default: all)")
    p.add_argument("--frames", help="START:END frames of every condition to train on (END exclusive), "
                                    "e.g. 0:1576; keep the test frames out")
    p.add_argument("--tolerance", type=int,
                   help="ground-truth tolerance in frames (NetVLAD's positives; default 0)")
    p.add_argument("--steps", type=int, help="number of training steps (default: the preset's)")
    p.add_argument("--max-minutes", type=float, help="stop (and save) after this much wall-clock time")
    p.add_argument("--preset", choices=("default", "small", "tiny"), default="default",
                   help="default: the method's standard setting (CALC: the original network); "
                        "small: CALC at half resolution and width (CALC only); tiny: a seconds-long "
                        "run for tests")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", default=[],
                   help="override a setting, e.g. --set train.lr=1e-4 --set model.clusters=32 (repeatable)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads (default: torch's own choice)")
    p.set_defaults(func=run)


def _method_module(method: str):
    if method == "calc":
        from fdnet.descriptors import calc as module
    else:
        from fdnet.descriptors import netvlad as module
    return module


def build_config(args):
    """The run config from the preset (or the run being resumed), the data flags and --set."""
    import dataclasses

    from fdnet.config import parse_overrides, replace_dotted
    from fdnet.errors import ConfigError

    module = _method_module(args.method)
    if args.resume:
        config = module.load_run_config(args.out)
    else:
        if args.preset not in module.PRESETS:
            raise ConfigError(f"--preset {args.preset}: {args.method} has presets {', '.join(module.PRESETS)}")
        config = module.PRESETS[args.preset]()
    # Data flags are set on the dataclass directly rather than through replace_dotted, whose YAML
    # parsing would read a frame range such as "10:20" as a base-60 integer.
    data = config.data
    if args.data is not None:
        data = dataclasses.replace(data, root=str(args.data))
    if args.conditions is not None:
        data = dataclasses.replace(data, conditions=[c.strip() for c in args.conditions.split(",") if c.strip()])
    if args.frames is not None:
        data = dataclasses.replace(data, frames=str(args.frames))
    if args.tolerance is not None:
        data = dataclasses.replace(data, tolerance=int(args.tolerance))
    config = dataclasses.replace(config, data=data)
    if args.steps is not None:
        config = replace_dotted(config, {"train.steps": int(args.steps)})
    return replace_dotted(config, parse_overrides(args.set))


def run(args) -> int:
    import torch

    from fdnet.training import baselines

    if args.threads is not None:
        torch.set_num_threads(max(1, args.threads))
    config = build_config(args)
    train = baselines.train_calc if args.method == "calc" else baselines.train_netvlad
    summary = train(config, args.out, resume=args.resume, max_minutes=args.max_minutes,
                    log=lambda line: print(line, flush=True))
    print(f"{args.method}: {summary['steps']} steps, final loss {summary['loss']:.4f}, "
          f"{summary['seconds']:.0f} s; use it with --method {args.method} --checkpoint {args.out}")
    return 0
