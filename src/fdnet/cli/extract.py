"""`fdnet extract`: FDNet content and appearance vectors for a folder of images, to .npz."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("extract", help="write FDNet content/appearance vectors of a folder of images to .npz",
                       description="Writes FILE.npz with arrays: content (N, L) L2-normalised content vectors "
                       "(the place descriptor), appearance (N, L) raw appearance vectors, names (N,) image file "
                       "names; row i is image i in natural file-name order (frame_2 before frame_10), the "
                       "order every fdnet command uses.")
    p.add_argument("--checkpoint", required=True, help="run directory of `fdnet train` (or its best/ sub-folder)")
    p.add_argument("--images", required=True, help="folder of images")
    p.add_argument("--out", required=True, help="output .npz file (written atomically)")
    p.add_argument("--batch-size", type=int, default=256, help="images per batch")
    p.add_argument("--bf16", action="store_true", help="bfloat16 autocast (faster on CPUs with AMX/AVX512-BF16)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: all cores)")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from fdnet.cli.common import set_threads
    from fdnet.data.images import list_images, load_images
    from fdnet.io import atomic_path, ensure_writable
    from fdnet.methods.fdnet.descriptor import FDNetDescriptor

    out = args.out if str(args.out).endswith(".npz") else f"{args.out}.npz"
    ensure_writable(out, what="vectors file")  # before loading the model and every image
    paths = list_images(args.images)
    set_threads(args.threads)
    model = FDNetDescriptor(checkpoint=args.checkpoint, bf16=args.bf16)
    content, appearance = [], []
    for start in range(0, len(paths), args.batch_size):
        images = load_images(paths[start:start + args.batch_size], model.input_size)
        content.append(model.describe(images))
        appearance.append(model.describe_appearance(images))
    with atomic_path(out) as tmp:
        with open(tmp, "wb") as handle:  # a file handle: np.savez would append .npz to the temp name
            np.savez(handle, content=np.concatenate(content), appearance=np.concatenate(appearance),
                     names=np.array([p.name for p in paths]))
    print(f"fdnet extract: {len(paths)} images -> {out} (content and appearance, length {model.dim})")
    return 0
