"""`fdnet vocabulary build`: learn a DBoW vocabulary tree from folders of training images."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("vocabulary", help="DBoW vocabulary tools (build a vocabulary tree)")
    actions = p.add_subparsers(dest="vocabulary_action", metavar="ACTION")
    b = actions.add_parser(
        "build",
        help="learn an ORB vocabulary tree (k-means on binary descriptors, TF-IDF) for --method dbow",
        description="Learn a DBoW2-style vocabulary tree from ORB features of the images in one or more "
        "folders; use it with `--method dbow --vocabulary FILE`. Learn it from images other "
        "than the ones you evaluate on.",
    )
    b.add_argument("--images", nargs="+", required=True, metavar="DIR", help="folders of training images")
    b.add_argument("--out", required=True, metavar="FILE", help="vocabulary file to write (.safetensors)")
    b.add_argument("--branching", type=int, default=10, metavar="K", help="children per node (default 10)")
    b.add_argument("--depth", type=int, default=4, metavar="L", help="tree depth; at most K^L words (default 4)")
    b.add_argument(
        "--max-images",
        type=int,
        default=None,
        metavar="N",
        help="use at most N images, spread evenly over all folders (default: all)",
    )
    b.add_argument("--features", type=int, default=500, metavar="N", help="ORB features per image (default 500)")
    b.add_argument(
        "--size",
        type=int,
        nargs=2,
        default=(288, 512),
        metavar=("H", "W"),
        help="image size for ORB (default 288 512; use the same as --method dbow)",
    )
    b.add_argument("--seed", type=int, default=0, help="k-means++ seed (default 0)")
    b.set_defaults(func=run)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def run(args) -> int:
    import numpy as np

    from fdnet.data.images import list_images
    from fdnet.descriptors.dbow import ORBSettings, learn_vocabulary
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable

    ensure_writable(args.out, what="vocabulary file")  # before the minutes of ORB work
    if args.max_images is not None and args.max_images < 1:
        raise ConfigError(f"--max-images must be >= 1, got {args.max_images}")
    if args.features < 1:
        raise ConfigError(f"--features must be >= 1, got {args.features}")
    paths = [p for folder in args.images for p in list_images(folder)]
    if args.max_images is not None and len(paths) > args.max_images:
        paths = [paths[i] for i in np.linspace(0, len(paths) - 1, args.max_images).round().astype(int)]
    vocab = learn_vocabulary(
        paths,
        tuple(args.size),
        ORBSettings(nfeatures=args.features),
        branching=args.branching,
        depth=args.depth,
        seed=args.seed,
        progress=True,
    )
    vocab.info["images"] = [str(f) for f in args.images]
    vocab.save(args.out)
    print(
        f"wrote {args.out}: {vocab.num_words} words (k={vocab.branching}, L={vocab.depth}) from "
        f"{vocab.info['training_features']} ORB features of {len(paths)} images"
    )
    return 0
