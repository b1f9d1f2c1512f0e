"""`fdnet extract`: any method's vectors for a folder of images (or a video or ROS bag), to .npz.

Parses the flags, builds the descriptor and calls :func:`fdnet.descriptors.extraction.extract`
(streaming: memory stays a few batches whatever the folder's size; the file is replaced
atomically at the end).
"""

from __future__ import annotations

from fdnet.cli.common import add_device_argument, add_method_arguments, add_pipeline_arguments

#: the method extracted when --method is not given (what `fdnet extract --checkpoint RUN` always meant)
DEFAULT_METHOD = "fdnet"
#: folder size from which --compile auto compiles (its one-off cost is then a few percent)
COMPILE_FROM = 50_000


def register(sub) -> None:
    from fdnet.cli.common import thread_count

    p = sub.add_parser("extract", help="write a method's vectors of a folder of images to .npz (default: FDNet's "
                                       "content and appearance vectors)",
                       description="Writes FILE.npz with arrays: descriptors (N, D) the method's vectors (what it "
                       "compares; for FDNet instead content (N, L) L2-normalised content vectors, the place "
                       "descriptor, and appearance (N, L) raw appearance vectors), names (N,) image file names, "
                       "sources (N,) the folder, video or bag of each image, timestamps (N,) seconds of video and "
                       "bag frames (NaN for image files), method and settings (JSON); row i is image i in natural "
                       "file-name order (frame_2 before frame_10), the order every fdnet command uses. A method "
                       "that learns from images (--fit) and is given none learns from the images it describes. "
                       "Images stream through the model in batches (decoded in worker processes) and the vectors "
                       "are written in chunks: memory stays a few batches whatever the folder's size. The .npz is "
                       "uncompressed and replaces --out atomically at the end.")
    add_method_arguments(p, required=False)
    p.add_argument("--images", required=True, help="folder of images, video file or ROS bag")
    p.add_argument("--out", required=True, help="output .npz file (written atomically)")
    add_pipeline_arguments(p, batch_size=256)
    add_device_argument(p)
    precision = p.add_mutually_exclusive_group()
    precision.add_argument("--bf16", action="store_true",
                           help="bfloat16 autocast (methods with a bf16 setting: fdnet, calc, ...): about 3x faster "
                                "where the device runs bf16 natively (CPUs with AVX512-BF16/AMX, Ampere and newer "
                                "GPUs); vectors within cosine 0.999 of fp32, R@1 within 0.5 points "
                                "(docs/performance.md)")
    precision.add_argument("--fp32", action="store_true",
                           help="float32 throughout: the default, as every other command computes")
    p.add_argument("--compile", choices=("auto", "on", "off"), default="auto",
                   help="torch.compile FDNet's content encoder first: compiling takes up to a minute on 2 CPU "
                        "cores, then the cpu preset ran 1.7x faster than bf16 eager (docs/performance.md). "
                        f"auto (default): on for folders of at least {COMPILE_FROM:,} images; falls back to eager "
                        "if compiling fails")
    p.add_argument("--threads", type=thread_count(), help="torch CPU threads (default: all cores)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def descriptor_options(args, method: str, count: int) -> dict:
    """Precision, compiling and batch size for the methods whose descriptor takes them. float32
    unless --bf16: one default for every command (a database or calibration made with vectors of
    `extract` then matches what `evaluate`, `match` and `loop-closure` compute)."""
    import inspect

    from fdnet.descriptors.registry import descriptor_class

    params = inspect.signature(descriptor_class(method).__init__).parameters
    bf16 = bool(args.bf16)
    wanted = {"compile": args.compile == "on" or (args.compile == "auto" and count >= COMPILE_FROM),
              "batch_size": args.batch_size}
    if "bf16" in params:
        wanted["bf16"] = bf16
    return {k: v for k, v in wanted.items() if k in params}


def run(args) -> int:
    from fdnet.cli.common import check_pipeline_arguments, method_options, set_threads
    from fdnet.data.images import list_images
    from fdnet.descriptors import create
    from fdnet.descriptors.extraction import extract
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable

    check_pipeline_arguments(args)
    if not args.method and len(args.checkpoint) == 1 and "=" not in args.checkpoint[0]:
        from fdnet.runs import recorded_method

        args.method = recorded_method(args.checkpoint[0])  # the run says which method trained it
    args.method = args.method or DEFAULT_METHOD
    if "," in args.method:
        raise ConfigError(f"--method {args.method}: extract writes one method's vectors; name one")
    out = args.out if str(args.out).endswith(".npz") else f"{args.out}.npz"
    ensure_writable(out, what="vectors file")  # before loading the model and every image
    paths = list_images(args.images)
    set_threads(args.threads)
    options = {**descriptor_options(args, args.method, len(paths)), **method_options(args, args.method)}
    descriptor = create(args.method, device=args.device, **options)
    summary = extract(descriptor, paths, out, batch_size=args.batch_size, workers=args.workers,
                      progress=not args.no_progress)
    device = getattr(descriptor, "device", "cpu")
    precision = "bf16" if getattr(descriptor, "bf16", False) else "fp32"
    print(f"fdnet extract: {summary['images']} images -> {out} ({args.method}: {' and '.join(summary['arrays'])}, "
          f"length {summary['dim']}; {device}, {precision}{', compiled' if getattr(descriptor, 'compiled', False) else ''}, "
          f"{summary['images_per_second']:.1f} images/s"
          + (f"; learnt from {summary['fitted_on']}" if summary["fitted_on"] else "") + ")")
    return 0
