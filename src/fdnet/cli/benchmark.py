"""`fdnet benchmark`: extraction ms/image and matching ms/query, with ratios against references
measured in the same run and the paper's Table 2 GPU figures."""

from __future__ import annotations

DEFAULT_METHODS = "raw,sad,hog,gist,dbow,conv3,landmarks"


def register(sub) -> None:
    p = sub.add_parser(
        "benchmark",
        help="time extraction (ms/image) and matching (ms/query) on this machine",
        description="Prints FDNet extraction time (fp32 eager vs bf16+channels_last) at the paper's 224x224 "
                    "size for L = 256..2048, matching time against a map, and every method's extraction "
                    "time, each with a ratio to the paper's TITAN X figure or a reference measured in the "
                    "same run.",
    )
    p.add_argument("--threads", type=int, default=2, help="torch threads (default 2, CI's core count)")
    p.add_argument("--methods", default=DEFAULT_METHODS,
                   help=f"comma-separated methods to time through the descriptor interface (default {DEFAULT_METHODS}); "
                        "add e.g. fdnet with --checkpoint fdnet=RUN_DIR")
    p.add_argument("--checkpoint", action="append", default=[], metavar="METHOD=RUN_DIR",
                   help="checkpoint for a trained method (repeatable)")
    p.add_argument("--images", help="folder of images to time methods on (default: a synthetic route)")
    p.add_argument("--num-images", type=int, default=32, help="images per method timing (default 32)")
    p.add_argument("--map-size", type=int, default=1000,
                   help="references in the matching map (default 1000, the Nordland test split here)")
    p.add_argument("--lengths", default="256,512,1024,2048", help="FDNet vector lengths to time")
    p.add_argument("--quick", action="store_true", help="fewer repeats and only L=512 (for smoke tests)")
    p.add_argument("--json", help="write all figures as JSON")
    p.set_defaults(func=run)


def _images(args, size):
    import numpy as np

    from fdnet.data.images import list_images, load_images

    if args.images:
        paths = list_images(args.images)[: args.num_images]
        return load_images(paths, size)
    from fdnet.data.synthetic import render_route

    frames = render_route(frames=args.num_images, conditions=("summer",), seed=0, size=tuple(size))
    return np.asarray(frames["summer"], dtype=np.float32)


def run(args) -> int:
    import json
    import platform

    import torch

    from fdnet import runtime
    from fdnet.descriptors import create
    from fdnet.errors import ConfigError, FdnetError
    from fdnet.io import atomic_write_text

    torch.set_num_threads(args.threads)
    repeats = 2 if args.quick else 5
    report: dict = {"threads": args.threads, "machine": platform.processor() or platform.machine()}
    print(f"fdnet benchmark: {args.threads} torch threads, {platform.machine()}")

    gflops = runtime.gemm_gflops(repeats=repeats)
    report["gemm_gflops_fp32"] = gflops
    print(f"\nmachine reference: fp32 GEMM 1024^3 = {gflops:.1f} GFLOP/s")

    lengths = [512] if args.quick else [int(v) for v in args.lengths.split(",")]
    print("\nFDNet extraction, `paper` preset architecture (224x224, 5 blocks 64..512), ms/image")
    print(f"{'L':>5} {'fp32 b32':>9} {'bf16 b32':>9} {'bf16/fp32':>9} {'fp32 b1':>8} {'bf16 b1':>8} "
          f"{'paper GPU':>9} {'paper/ours':>10}")
    report["fdnet_extraction_ms"] = {}
    for length in lengths:
        t = runtime.fdnet_extraction(vector_length=length, repeats=repeats)
        paper = runtime.PAPER_TABLE2.get(length, (float("nan"), float("nan")))[0]
        best = min(t["bf16_batch32"], t["fp32_batch32"])
        report["fdnet_extraction_ms"][length] = dict(t, paper_gpu=paper)
        print(f"{length:>5} {t['fp32_batch32']:>9.2f} {t['bf16_batch32']:>9.2f} "
              f"{t['fp32_batch32'] / t['bf16_batch32']:>8.2f}x {t['fp32_batch1']:>8.2f} {t['bf16_batch1']:>8.2f} "
              f"{paper:>9.1f} "
              f"{paper / best:>9.2f}x")

    print(f"\nMatching: best of {args.map_size} references per query, ms/query")
    print(f"{'L':>5} {'numpy 1q':>9} {'numpy batch':>11} {'faiss flat':>10} {'faiss hnsw':>10} {'paper GPU':>9} {'paper/ours':>10}")
    report["matching_ms"] = {}
    for length in lengths:
        m = runtime.matching_per_query(args.map_size, length)
        paper = runtime.PAPER_TABLE2.get(length, (float("nan"), float("nan")))[1]
        report["matching_ms"][length] = dict(m, paper_gpu=paper)
        print(f"{length:>5} {m['numpy_single']:>9.4f} {m['numpy_batched']:>11.4f} {m['faiss_flat']:>10.4f} "
              f"{m['faiss_hnsw']:>10.4f} {paper:>9.2f} {paper / m['numpy_single']:>9.1f}x")

    checkpoints = {}
    for item in args.checkpoint:
        if "=" not in item:
            raise ConfigError(f"--checkpoint {item!r}: expected METHOD=RUN_DIR")
        method, path = item.split("=", 1)
        checkpoints[method.strip()] = path
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    methods += [m for m in checkpoints if m not in methods]
    print(f"\nExtraction through the descriptor interface, {args.num_images} images, ms/image "
          f"(decoding excluded); ratio = SAD's time / method's time")
    report["method_extraction_ms"] = {}
    cache = {}
    for method in methods:
        try:
            descriptor = create(method, checkpoint=checkpoints.get(method))
            size = tuple(descriptor.input_size)
            if size not in cache:
                cache[size] = _images(args, size)
            images = cache[size]
            if descriptor.needs_fit:
                descriptor.fit(images)
            ms = runtime.descriptor_extraction(descriptor, images, repeats=max(1, repeats - 2))
        except FdnetError as exc:
            print(f"  {method:10s} skipped: {exc}")
            report["method_extraction_ms"][method] = None
            continue
        report["method_extraction_ms"][method] = ms
        print(f"  {method:10s} {ms:9.3f} ms/image  ({descriptor.dim}-d, input {size[0]}x{size[1]})")
    sad = report["method_extraction_ms"].get("sad")
    if sad:
        for method, ms in report["method_extraction_ms"].items():
            if ms:
                report.setdefault("ratio_vs_sad", {})[method] = sad / ms
    if args.json:
        atomic_write_text(args.json, json.dumps(report, indent=2))
        print(f"\nwrote {args.json}")
    return 0
