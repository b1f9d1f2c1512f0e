"""`fdnet extract`: any method's vectors for a folder of images (or a video or ROS bag), to .npz
or to hloc's global-features .h5 (``--format h5``).

Parses the flags, builds the descriptor and calls :func:`fdnet.tasks.extract.extract`
(or :func:`~fdnet.tasks.extract.extract_h5`; streaming: memory stays a few batches
whatever the folder's size; the file is replaced atomically at the end). Under
``torchrun --nproc-per-node N -m fdnet extract ...`` every process describes its share of the
images and rank 0 writes the file (:mod:`fdnet.descriptors.sharding`).
"""

from __future__ import annotations

from fdnet.cli.common import add_device_argument, add_method_arguments, add_pipeline_arguments

#: the method extracted when --method is not given (what `fdnet extract --checkpoint RUN` always meant)
DEFAULT_METHOD = "fdnet"
#: folder size from which --compile auto compiles (its one-off cost is then a few percent)
COMPILE_FROM = 50_000
#: --format's choices and the suffixes that say each
FORMAT_SUFFIXES = {"npz": (".npz",), "h5": (".h5", ".hdf5")}


def register(sub) -> None:
    from fdnet.cli.common import thread_count

    p = sub.add_parser(
        "extract",
        help="write a method's vectors of a folder of images to .npz (default: FDNet's "
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
        "uncompressed and replaces --out atomically at the end. --format h5 writes hloc's "
        'global-features file instead (docs/guide.md, "hloc").',
    )
    add_method_arguments(p, required=False)
    p.add_argument("--images", required=True, help="folder of images, video file or ROS bag")
    p.add_argument(
        "--recursive",
        action="store_true",
        help="the images of --images' whole tree (sub-folders too, hidden ones left out), in natural "
        "order of their paths below it; with --format h5 they are named by that path "
        "(db/0001.jpg), as hloc names the images of an image_dir holding db/ and query/ (the "
        ".npz keeps file names in names and each image's folder in sources)",
    )
    p.add_argument("--out", required=True, help="output file, .npz or .h5 (written atomically)")
    p.add_argument(
        "--format",
        choices=tuple(FORMAT_SUFFIXES),
        default=None,
        help="npz (default): fdnet's arrays above. h5: hloc's global-features file "
        "(cvg/Hierarchical-Localization): one group per image holding its place descriptor "
        "(descriptors, or FDNet's content) as global_descriptor, float32, the image named by its "
        "path relative to the --images folder (a video's or bag's: relative to the folder holding "
        "it), so hloc's image_dir is that folder. Default: from --out's suffix (.h5 or .hdf5: h5)",
    )
    add_pipeline_arguments(p, batch_size=256)
    add_device_argument(p)
    precision = p.add_mutually_exclusive_group()
    precision.add_argument(
        "--bf16",
        action="store_true",
        help="bfloat16 autocast (methods with a bf16 setting: fdnet, calc, ...): about 2x faster "
        "where the device runs bf16 natively (CPUs with AVX512-BF16/AMX, Ampere and newer "
        "GPUs); vectors within cosine 0.999 of fp32, R@1 within 0.5 points "
        "(docs/performance.md)",
    )
    precision.add_argument(
        "--fp32", action="store_true", help="float32 throughout: the default, as every other command computes"
    )
    p.add_argument(
        "--compile",
        choices=("auto", "on", "off"),
        default="auto",
        help="torch.compile FDNet's content encoder first: compiling takes up to a minute on 2 CPU "
        "cores, and on the CPU the cpu preset then ran no faster than eager in forward passes sized "
        f"to the cache (docs/performance.md). auto (default): on for folders of at least {COMPILE_FROM:,} "
        "images on a GPU, off on the CPU; falls back to eager if compiling fails",
    )
    p.add_argument("--threads", type=thread_count(), help="torch CPU threads (default: all cores)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def descriptor_options(args, method: str, count: int) -> dict:
    """Precision, compiling and batch size for the methods whose descriptor takes them. float32
    unless --bf16: one default for every command (a database or calibration made with vectors of
    `extract` then matches what `evaluate`, `match` and `loop-closure` compute)."""
    from fdnet.descriptors.registry import setting_names

    params = setting_names(method)
    bf16 = bool(args.bf16)
    wanted = {
        "compile": compiles(args, count),
        "batch_size": args.batch_size,
    }
    if "bf16" in params:
        wanted["bf16"] = bf16
    return {k: v for k, v in wanted.items() if k in params}


def compiles(args, count: int) -> bool:
    """Whether ``--compile`` (on, off or auto) compiles for ``count`` images on ``--device``:
    auto compiles from :data:`COMPILE_FROM` images on a GPU only (on the CPU it measured no
    faster than eager passes sized to the cache)."""
    from fdnet.backbones import resolve_device

    if args.compile != "auto":
        return args.compile == "on"
    return count >= COMPILE_FROM and resolve_device(getattr(args, "device", "auto"), where="--device").type != "cpu"


def run(args) -> int:
    """The command, in one process or in each process of a torchrun launch
    (:mod:`fdnet.descriptors.sharding`: each describes its block of the images, rank 0 writes
    --out and alone prints)."""
    from fdnet.descriptors.sharding import launch

    with launch() as shards:
        return _run(args, shards)


def _refuse_writing_an_input(args, out) -> None:
    """--out naming a file the command reads (the vectors of --method precomputed, a model, a
    vocabulary) would replace it with the new vectors: refused before any work."""
    import os

    from fdnet.cli.common import method_labels, split_scope
    from fdnet.descriptors.registry import available_methods
    from fdnet.errors import ConfigError

    scopes = set(available_methods()) | set(method_labels(args))
    for option in ("vectors", "weights", "vocabulary", "checkpoint"):
        for value in getattr(args, option, None) or []:
            path = value if os.path.exists(str(value)) else split_scope(value, scopes)[1]
            try:
                same = os.path.samefile(out, path)
            except OSError:  # one of them does not exist
                same = False
            if same:
                raise ConfigError(
                    f"--out {out} is the --{option} file the command reads; writing it would "
                    "destroy it: give another name"
                )


def _prepare(args, shards):
    """``(out_format, out, paths, root, descriptor)``: every check that can refuse the command, in
    the order that refuses before the slow work (loading the model and every image); the output
    is checked by rank 0 alone, which writes it."""
    from fdnet.cli.common import check_pipeline_arguments, method_options, set_threads, split_scope
    from fdnet.data.images import list_images
    from fdnet.descriptors import create
    from fdnet.descriptors.registry import available_methods
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable

    check_pipeline_arguments(args)
    bare_run = len(args.checkpoint) == 1 and split_scope(args.checkpoint[0], available_methods())[0] is None
    if not args.method and bare_run:
        from fdnet.runs import recorded_method

        args.method = recorded_method(args.checkpoint[0])  # the run says which method trained it
    args.method = args.method or DEFAULT_METHOD
    if "," in args.method:
        raise ConfigError(f"--method {args.method}: extract writes one method's vectors; name one")
    out_format, out = output_format(args.format, args.out)
    _refuse_writing_an_input(args, out)
    if shards.is_main:
        ensure_writable(out, what="vectors file")  # before loading the model and every image
    if out_format == "h5":
        from fdnet.descriptors.hloc_formats import image_root, require_h5py

        require_h5py()  # a missing h5py is said before any work
    paths = list_images(args.images, recursive=args.recursive)
    root = None
    if out_format == "h5":
        from fdnet.descriptors.hloc_formats import check_image_name, relative_names

        root = image_root([args.images])
        for name in relative_names(paths, root):  # a name hloc's file cannot hold: said before loading the model
            check_image_name(name, out)
    set_threads(args.threads or shards.threads())
    options = {**descriptor_options(args, args.method, len(paths)), **method_options(args, args.method)}
    descriptor = create(args.method, device=args.device, **options)
    shards.check_device(descriptor.device)
    return out_format, out, paths, root, descriptor


def _run(args, shards) -> int:
    from fdnet.tasks.extract import extract

    out_format, out, paths, root, descriptor = shards.collectively(lambda: _prepare(args, shards))
    if out_format == "h5":
        from fdnet.tasks.extract import extract_h5

        summary = extract_h5(
            descriptor,
            paths,
            out,
            root,
            batch_size=args.batch_size,
            workers=args.workers,
            progress=not args.no_progress,
        )
        written = f"{summary['array']} as hloc's global_descriptor"
    else:
        summary = extract(
            descriptor, paths, out, batch_size=args.batch_size, workers=args.workers, progress=not args.no_progress
        )
        written = " and ".join(summary["arrays"])
    device = descriptor.device or "cpu"
    precision = "bf16" if getattr(descriptor, "bf16", False) else "fp32"
    processes = f"{shards.world_size} processes, " if shards.world_size > 1 else ""
    print(
        f"fdnet extract: {summary['images']} images -> {out} ({args.method}: {written}, "
        f"length {summary['dim']}; {processes}{device}, {precision}"
        f"{', compiled' if getattr(descriptor, 'compiled', False) else ''}, "
        f"{summary['images_per_second']:.1f} images/s"
        + (f"; learnt from {summary['fitted_on']}" if summary["fitted_on"] else "")
        + ")"
    )
    if out_format == "h5":
        print(f"fdnet extract: image names are relative to {summary['root']} (hloc's image_dir)")
    return 0


def output_format(given: str | None, out: str) -> tuple[str, str]:
    """(format, output path) from --format and --out: the format --out's suffix says when
    --format is not given (npz unless .h5/.hdf5), the format's suffix added to an --out with
    none of its own (``vectors`` -> ``vectors.npz``); a suffix that says the other
    format is refused."""
    from fdnet.errors import ConfigError

    out = str(out)
    said = next((name for name, suffixes in FORMAT_SUFFIXES.items() if out.lower().endswith(suffixes)), None)
    if given is not None and said is not None and said != given:
        raise ConfigError(
            f"--format {given} --out {out}: the file name says {said}; give --out with "
            f"{' or '.join(FORMAT_SUFFIXES[given])}, or --format {said}"
        )
    chosen = given or said or "npz"
    return chosen, out if said == chosen else f"{out}{FORMAT_SUFFIXES[chosen][0]}"
