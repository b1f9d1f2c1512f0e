"""`fdnet demo`: the main job end to end on an embedded SYNTHETIC route (no download).

1. ``fdnet synth``: render a route under summer/autumn/winter/night;
2. ``fdnet train``: train FDNet (``cpu`` preset) on the first part of the route, all conditions,
   no place labels, validating on a held-out middle part;
3. ``fdnet evaluate``: FDNet against the trunk it reads (alone and PCA-whitened to 512 on the
   training frames) and the SAD (SeqSLAM front end) and HOG baselines on the last part of the
   route, night -> summer and winter -> summer, with tables, JSON and plots.

Each step is the documented command, run in-process, so the demo shows exactly what a user types.
"""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("demo", help="the main job on a synthetic route: synth, train FDNet, evaluate vs baselines",
                       description="Generate a synthetic multi-condition route, train FDNet (cpu preset) on its "
                                   "first part and evaluate FDNet, SAD and HOG on its last part. Needs no download.")
    p.add_argument("--out", default="demo-out", help="output folder (default demo-out)")
    p.add_argument("--frames", type=int, default=400, help="frames per condition (default 400)")
    p.add_argument("--train-minutes", type=float, default=9.0,
                   help="training time budget in minutes (default 9; training stops early with a checkpoint)")
    p.add_argument("--preset", default="cpu", help="training preset (default cpu; tiny for a smoke test)")
    p.add_argument("--methods", default="fdnet,trunk,trunk-whitened,sad,hog",
                   help="methods to compare (default fdnet,trunk,trunk-whitened,sad,hog: trunk is the frozen map FDNet "
                        "reads and trunk-whitened its PCA-whitening to 512 fitted on the training frames, the rows "
                        "to beat)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resume", action="store_true", help="continue an interrupted demo training run")
    p.set_defaults(func=run)


def run(args) -> int:
    import time
    from pathlib import Path

    from fdnet.cli import main
    from fdnet.errors import ConfigError

    if args.frames < 40:
        raise ConfigError(f"--frames must be at least 40 for a train/validation/test split, got {args.frames}")
    out = Path(args.out)
    from fdnet.io import ensure_writable

    ensure_writable(out, what="demo output", directory=True)  # a file or read-only path: refused first
    route, run_dir = out / "route", out / "fdnet-run"
    train_end = int(args.frames * 0.625)        # 0:250 of 400 trains
    val_end = int(args.frames * 0.75)           # 250:300 validates (checkpoint selection)
    test = f"{val_end}:{args.frames}"           # 300:400 tests, never seen in training
    started = time.perf_counter()

    def step(title: str, argv: list[str]) -> None:
        print(f"\n=== {title}\n$ fdnet {' '.join(argv)}", flush=True)
        code = main(argv)
        if code:
            raise SystemExit(code)

    step("1/3 synthetic route (SYNTHETIC images, a demo and test route, not a benchmark)",
         ["synth", "--out", str(route), "--frames", str(args.frames), "--seed", str(args.seed)])
    train = ["train", "--data", str(route), "--preset", args.preset, "--out", str(run_dir),
             "--frames", f"0:{train_end}", "--max-minutes", str(args.train_minutes),
             "--validate-reference", "summer", "--validate-query", "night",
             "--validate-frames", f"{train_end}:{val_end}", "--validate-tolerance", "1",
             "--set", f"runtime.seed={args.seed}"]
    if args.resume:
        train = [a for a in train if a not in ("--preset", args.preset)] + ["--resume"]
    step("2/3 train FDNet on frames 0:%d of every condition (no place labels)" % train_end, train)
    methods = args.methods
    from fdnet import runs
    from fdnet.methods.fdnet.config import TrainConfig

    if runs.load_config(run_dir, TrainConfig).model.backbone == "none":
        # a preset whose encoders read pixels has no trunk to compare with
        methods = ",".join(m for m in methods.split(",") if not m.strip().startswith("trunk"))
    fit = ["--fit", str(route), "--fit-frames", f"0:{train_end}"] if "trunk-whitened" in methods.split(",") else []
    for query in ("night", "winter"):
        step(f"3/3 evaluate {query} -> summer on frames {test} (tolerance 1 frame)",
             ["evaluate", "--data", str(route), "--reference", "summer", "--query", query,
              "--frames", test, "--tolerance", "1", "--method", methods, "--checkpoint", str(run_dir), *fit,
              "--json", str(out / f"results-{query}-summer.json"), "--plots", str(out / f"plots-{query}-summer")])
    minutes = (time.perf_counter() - started) / 60
    print(f"\ndemo finished in {minutes:.1f} min; results, plots and the trained run are in {out}/")
    return 0
