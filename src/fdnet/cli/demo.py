"""`fdnet demo`: the main job end to end on an embedded SYNTHETIC route (no download):
synthesise, train FDNet, evaluate it against baselines (:func:`fdnet.demo.run_demo`, which
prints the equivalent `fdnet synth/train/evaluate` command line before each step)."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="the main job on a synthetic route: synth, train FDNet, evaluate vs baselines",
        description="Generate a synthetic multi-condition route, train FDNet (cpu preset) on its "
        "first part and evaluate FDNet, SAD and HOG on its last part. Needs no download.",
    )
    p.add_argument("--out", default="demo-out", help="output folder (default demo-out)")
    p.add_argument("--num-frames", type=int, default=400, help="frames per condition (default 400)")
    p.add_argument(
        "--max-minutes",
        type=float,
        default=9.0,
        help="training time budget in minutes (default 9; training stops early with a checkpoint)",
    )
    p.add_argument("--preset", default="cpu", help="training preset (default cpu; tiny for a smoke test)")
    p.add_argument(
        "--method",
        default="fdnet,trunk,trunk-whitened,sad,hog",
        help="methods to compare, comma-separated (default fdnet,trunk,trunk-whitened,sad,hog: trunk is "
        "the frozen map FDNet reads and trunk-whitened its PCA-whitening to 512 fitted on the "
        "training frames, the rows to beat)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resume", action="store_true", help="continue an interrupted demo training run")
    p.set_defaults(func=run)


def run(args) -> int:
    from fdnet.demo import DemoSettings, run_demo

    settings = DemoSettings(
        num_frames=args.num_frames,
        max_minutes=args.max_minutes,
        preset=args.preset,
        methods=args.method,
        seed=args.seed,
        resume=args.resume,
    )
    run_demo(args.out, settings, say=lambda line: print(line, flush=True))
    return 0
