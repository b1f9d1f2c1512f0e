"""`fdnet extract`: FDNet content and appearance vectors for a folder of images, to .npz.

Streams: images are decoded in worker processes while the model runs, and the vectors are
written batch by batch to temporary ``.npy`` parts, packed into the ``.npz`` at the end and
renamed over ``--out`` (:class:`fdnet.descriptors.pipeline.NpzChunkWriter`), so a folder of any
size needs only a few batches of memory and a crash never leaves half a file.
"""

from __future__ import annotations

from fdnet.cli.common import add_device_argument, add_pipeline_arguments


#: folder size from which --compile auto compiles (its one-off cost is then a few percent)
COMPILE_FROM = 50_000


def register(sub) -> None:
    p = sub.add_parser("extract", help="write FDNet content/appearance vectors of a folder of images to .npz",
                       description="Writes FILE.npz with arrays: content (N, L) L2-normalised content vectors "
                       "(the place descriptor), appearance (N, L) raw appearance vectors, names (N,) image file "
                       "names, sources (N,) the folder, video or bag of each image, timestamps (N,) seconds of "
                       "video and bag frames (NaN for image files); row i is image i in natural file-name order (frame_2 before frame_10), the "
                       "order every fdnet command uses. Images stream through the model in batches (decoded "
                       "in worker processes) and the vectors are written in chunks: memory stays a few "
                       "batches whatever the folder's size. The .npz is uncompressed and replaces --out "
                       "atomically at the end.")
    p.add_argument("--checkpoint", required=True, help="run directory of `fdnet train` (or its best/ sub-folder)")
    p.add_argument("--images", required=True, help="folder of images, video file or ROS bag")
    p.add_argument("--out", required=True, help="output .npz file (written atomically)")
    add_pipeline_arguments(p, batch_size=256)
    add_device_argument(p)
    precision = p.add_mutually_exclusive_group()
    precision.add_argument("--bf16", action="store_true",
                           help="bfloat16 autocast with channels_last tensors (the default where the device runs "
                                "bf16 natively: CPUs with AVX512-BF16/AMX, Ampere and newer GPUs; R@1 within 0.5 "
                                "points of fp32 for a trained cpu-preset run, docs/performance.md)")
    precision.add_argument("--fp32", action="store_true",
                           help="float32 throughout (what `fdnet evaluate --method fdnet` computes by default)")
    p.add_argument("--compile", nargs="?", const="on", choices=("auto", "on", "off"), default="auto",
                   help="torch.compile FDNet's content encoder first: compiling takes up to a minute on 2 CPU "
                        "cores, then the cpu preset ran 1.7x faster than bf16 eager (docs/performance.md). "
                        f"auto (default): on for folders of at least {COMPILE_FROM:,} images; falls back to eager "
                        "if compiling fails; a bare --compile means on")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: all cores)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _frame_arrays(paths) -> dict:
    """``sources`` (N,): the video, bag or folder each image came from; ``timestamps`` (N,) seconds
    (a video's from its first frame, a bag's recording time since the epoch; NaN for image files)."""
    import numpy as np

    from fdnet.data.sources import frame_records

    records = frame_records(paths)
    return {"sources": np.array([r.source for r in records]),
            "timestamps": np.array([np.nan if r.timestamp is None else r.timestamp for r in records],
                                   dtype=np.float64)}


def run(args) -> int:
    import numpy as np

    from fdnet.cli.common import check_pipeline_arguments, set_threads
    from fdnet.data.images import list_images
    from fdnet.descriptors.pipeline import NpzChunkWriter, describe_stream
    from fdnet.io import ensure_writable
    from fdnet.methods.fdnet.descriptor import FDNetDescriptor

    check_pipeline_arguments(args)
    out = args.out if str(args.out).endswith(".npz") else f"{args.out}.npz"
    ensure_writable(out, what="vectors file")  # before loading the model and every image
    paths = list_images(args.images)
    set_threads(args.threads)
    bf16 = True if args.bf16 else False if args.fp32 else None  # None: where the device runs it natively
    model = FDNetDescriptor(checkpoint=args.checkpoint, device=args.device, bf16=bf16, batch_size=args.batch_size,
                            compile=args.compile == "on" or (args.compile == "auto" and len(paths) >= COMPILE_FROM))
    shape = (len(paths), model.dim)
    timing: dict = {}
    with NpzChunkWriter(out, {"content": (shape, np.float32), "appearance": (shape, np.float32)}) as writer:
        for _, (content, appearance) in describe_stream(
                model, paths, args.batch_size, workers=args.workers, timing=timing, describe=model.describe_both,
                progress=not args.no_progress, what="extract [fdnet]"):
            writer.write("content", content)
            writer.write("appearance", appearance)
        writer.close({"names": np.array([p.name for p in paths]), **_frame_arrays(paths)})
    rate = len(paths) / max(timing.get("seconds_wall", 0.0), 1e-9)
    print(f"fdnet extract: {len(paths)} images -> {out} (content and appearance, length {model.dim}; "
          f"{model.device}, {'bf16' if model.bf16 else 'fp32'}{', compiled' if model.compiled else ''}, "
          f"{rate:.1f} images/s)")
    return 0
