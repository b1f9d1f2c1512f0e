"""`fdnet benchmark`: extraction ms/image and matching ms/query on this machine, every figure
stated against references measured in the same run (fp32 and bf16 GEMM rates, FDNet's fp32
eager path) and against the paper's Table 2/5 (TITAN X); GPU figures when a GPU is present; and
indexed search on maps of 10^3-10^6 places (``--map-size``). Nothing here is asserted by tests:
machines are shared and noisy, so the command prints ratios measured side by side."""

from __future__ import annotations

DEFAULT_METHODS = "raw,sad,hog,gist,dbow,conv3,landmarks"
PARTS = ("fdnet", "api", "gpu", "matching", "methods", "scale")
DEFAULT_INDEXES = "flat,ivf,ivfpq,hnsw"


def register(sub) -> None:
    from fdnet.cli.common import add_device_argument

    p = sub.add_parser(
        "benchmark",
        help="time extraction (ms/image), matching (ms/query) and indexed search at scale on this machine",
        description="Prints, each with a ratio to a reference: this machine's fp32 and bf16 GEMM rates; FDNet "
                    "extraction at the paper's 224x224 for L = 256..2048 (fp32 eager vs bf16 + channels_last) "
                    "as a fraction of those rates and against the paper's TITAN X; the cpu preset's descriptor "
                    "through the public API (the fp32 eager path vs what `fdnet extract` runs); GPU images/s "
                    "(public API and forward only) when a GPU is present; matching time against a map; every "
                    "method's extraction time against SAD and the paper's Table 5; and, per --map-size, build "
                    "time, memory, ms/query and recall@1 against exact search of each faiss index.",
    )
    p.add_argument("--threads", type=int, default=2, help="torch and faiss threads (default 2, CI's core count)")
    p.add_argument("--parts", default=",".join(PARTS),
                   help=f"what to measure, comma-separated from {','.join(PARTS)} (default all; the GEMM "
                        "references are always measured)")
    p.add_argument("--methods", default=DEFAULT_METHODS,
                   help=f"comma-separated methods to time through the descriptor interface (default {DEFAULT_METHODS}); "
                        "add e.g. fdnet with --checkpoint fdnet=RUN_DIR")
    p.add_argument("--checkpoint", action="append", default=[], metavar="METHOD=RUN_DIR",
                   help="checkpoint for a trained method (repeatable)")
    p.add_argument("--images", help="folder of images to time methods on (default: a synthetic route)")
    p.add_argument("--num-images", type=int, default=32, help="images per method timing (default 32)")
    p.add_argument("--map-size", default="1000",
                   help="map sizes, comma-separated (e.g. 1000,100000,1000000): the first is the matching table's "
                        "map; each is a random map of the scale benchmark (default 1000)")
    p.add_argument("--indexes", default=DEFAULT_INDEXES,
                   help=f"faiss indexes of the scale benchmark (default {DEFAULT_INDEXES})")
    p.add_argument("--index-set", action="append", default=[], metavar="KIND:KEY=VALUE",
                   help="an index setting for the scale benchmark, e.g. ivf:ivf_probe=32 (repeatable)")
    p.add_argument("--sweep", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="measure each built index at several search-time settings without rebuilding it: "
                        "ivf_probe (ivf, ivfpq) or hnsw_ef_search (hnsw), e.g. --sweep ivf_probe=16,32,64")
    p.add_argument("--queries", type=int, default=1000, help="queries per map in the scale benchmark (default 1000)")
    p.add_argument("--noise", type=float, default=0.5,
                   help="norm of the noise added to a map vector to make a query (default 0.5: cosine ~0.9 to "
                        "its place)")
    p.add_argument("--scale-dim", type=int,
                   help="vector length of the random maps (default: FDNet's, 512, or that of --checkpoint fdnet=RUN)")
    p.add_argument("--map-vectors", metavar="FILE",
                   help="a real descriptor's vectors for the scale benchmark too: .npy (N, D) or an .npz from "
                        "`fdnet extract` (its content array)")
    p.add_argument("--query-vectors", metavar="FILE",
                   help="queries for --map-vectors (.npy/.npz); default: its vectors plus --noise")
    p.add_argument("--lengths", default="256,512,1024,2048", help="FDNet vector lengths to time")
    p.add_argument("--compile", action="store_true",
                   help="also time `fdnet extract --compile` (torch.compile; compiling takes about a minute)")
    p.add_argument("--quick", action="store_true", help="fewer repeats and only L=512 (for smoke tests)")
    p.add_argument("--json", help="write all figures as JSON")
    add_device_argument(p)
    p.set_defaults(func=run)


def _images(args, size, uint8: bool = False):
    import numpy as np

    from fdnet.data.images import list_images, load_image_uint8, load_images

    if args.images:
        paths = list_images(args.images)[: args.num_images]
        if uint8:
            return np.stack([load_image_uint8(p, size) for p in paths])
        return load_images(paths, size)
    from fdnet.data.synthetic import render_route

    frames = render_route(frames=args.num_images, conditions=("summer",), seed=0, size=tuple(size))
    images = np.asarray(frames["summer"], dtype=np.float32)
    if uint8:
        return np.clip(np.rint(images * 255.0), 0, 255).astype(np.uint8)
    return images


def _read_vectors(path: str, what: str):
    from pathlib import Path

    import numpy as np

    from fdnet.errors import DataError

    p = Path(path)
    if not p.is_file():
        raise DataError(f"{p}: {what} file not found")
    try:
        if p.suffix == ".npz":
            with np.load(p, allow_pickle=False) as z:
                key = "content" if "content" in z.files else (z.files[0] if len(z.files) == 1 else None)
                if key is None:
                    raise DataError(f"{p}: an .npz without a 'content' array (has {', '.join(z.files)})")
                v = z[key]
        else:
            from fdnet.data.arrays import load_npy

            v = load_npy(p, ndim=2, what=what)
    except (ValueError, OSError) as exc:
        raise DataError(f"{p}: cannot read {what} ({exc})") from None
    v = np.asarray(v, dtype=np.float32)
    if v.ndim != 2 or len(v) == 0 or not np.isfinite(v).all():
        raise DataError(f"{p}: {what} must be a finite (N, D) array with N > 0, got shape {v.shape}")
    return np.ascontiguousarray(v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12))


def _index_overrides(args):
    from fdnet.errors import ConfigError
    from fdnet.matching.index import INDEX_KINDS, parse_index_settings

    out: dict = {}
    for item in args.index_set:
        kind, sep, pair = item.partition(":")
        if not sep or kind not in INDEX_KINDS:
            raise ConfigError(f"--index-set {item!r}: expected KIND:KEY=VALUE with KIND one of {', '.join(INDEX_KINDS)}")
        settings = parse_index_settings(kind, [pair], where="--index-set")
        key = pair.split("=", 1)[0].strip()
        out.setdefault(kind, {})[key] = getattr(settings, key)
    return out


def _sweeps(args) -> dict:
    from fdnet.errors import ConfigError
    from fdnet.runtime import SWEEPABLE

    out = {}
    for item in args.sweep:
        key, sep, values = item.partition("=")
        key = key.strip()
        try:
            numbers = [int(v) for v in values.split(",") if v.strip()]
        except ValueError:
            numbers = []
        if not sep or key not in SWEEPABLE or not numbers or min(numbers) < 1:
            raise ConfigError(f"--sweep {item!r}: expected KEY=V1,V2,... with KEY one of {', '.join(SWEEPABLE)} "
                              "and whole numbers >= 1")
        out[key] = numbers
    return out


def run(args) -> int:
    import json
    import platform
    import sys
    import tempfile

    import torch

    from fdnet import __version__, runtime
    from fdnet.descriptors import create
    from fdnet.errors import ConfigError, FdnetError
    from fdnet.io import atomic_write_text, ensure_writable
    from fdnet.matching.index import INDEX_KINDS

    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        raise ConfigError(f"--parts: unknown {', '.join(unknown)}; choose from {','.join(PARTS)}")
    try:
        map_sizes = [int(v) for v in str(args.map_size).split(",") if v.strip()]
    except ValueError:
        raise ConfigError(f"--map-size {args.map_size!r}: expected whole numbers, e.g. 1000,100000") from None
    if not map_sizes or min(map_sizes) < 2:
        raise ConfigError(f"--map-size {args.map_size!r}: every map needs at least 2 places")
    kinds = [k.strip() for k in args.indexes.split(",") if k.strip()]
    for kind in kinds:
        if kind not in INDEX_KINDS:
            raise ConfigError(f"--indexes: unknown index {kind!r}; choose from {', '.join(INDEX_KINDS)}")
    if args.queries < 1 or args.num_images < 1 or args.threads < 1:
        raise ConfigError("--queries, --num-images and --threads must be at least 1")
    if args.noise < 0:
        raise ConfigError(f"--noise must be >= 0, got {args.noise}")
    overrides = _index_overrides(args)
    sweep = _sweeps(args)
    for flag, path in (("--map-vectors", args.map_vectors), ("--query-vectors", args.query_vectors)):
        if path is not None and not __import__("pathlib").Path(path).is_file():
            from fdnet.errors import DataError

            raise DataError(f"{path}: {flag} file not found")
    if args.query_vectors and not args.map_vectors:
        raise ConfigError("--query-vectors needs --map-vectors")
    if args.json:
        ensure_writable(args.json, what="benchmark JSON")
    checkpoints = {}
    for item in args.checkpoint:
        if "=" not in item:
            raise ConfigError(f"--checkpoint {item!r}: expected METHOD=RUN_DIR")
        method, path = item.split("=", 1)
        checkpoints[method.strip()] = path
    device = runtime.resolve_device(args.device)

    torch.set_num_threads(args.threads)
    try:
        import faiss

        faiss.omp_set_num_threads(args.threads)
    except ImportError:  # pragma: no cover - faiss is a dependency
        pass
    repeats = 2 if args.quick else 5
    cpu = runtime.cpu_model()
    report: dict = {"threads": args.threads, "machine": platform.processor() or platform.machine(), "cpu": cpu,
                    "torch": torch.__version__, "fdnet": __version__, "device": str(device),
                    "command": "fdnet " + " ".join(sys.argv[1:]) if sys.argv and "benchmark" in sys.argv else None}
    print(f"fdnet benchmark: {args.threads} threads, {cpu} ({platform.machine()}), torch {torch.__version__}, "
          f"device {device}")

    size = 1024 if args.quick else 2048
    gflops = runtime.gemm_gflops(size=size, repeats=repeats)
    bf16_gflops = runtime.gemm_gflops(size=size, repeats=repeats, dtype="bf16")
    native = runtime.bf16_native("cpu")
    report.update(gemm_gflops_fp32=gflops, gemm_gflops_bf16=bf16_gflops, gemm_size=size, bf16_native_cpu=native)
    print(f"\nmachine references, measured now: fp32 GEMM {size}^3 = {gflops:.1f} GFLOP/s, bf16 GEMM = "
          f"{bf16_gflops:.1f} GFLOP/s ({'native' if native else 'no native'} bf16 on this CPU)")

    lengths = [512] if args.quick else [int(v) for v in args.lengths.split(",")]
    if "fdnet" in parts:
        import dataclasses

        from fdnet.methods.fdnet.config import preset

        paper_model = preset("paper").model
        print("\nFDNet extraction, `paper` preset architecture (224x224, 5 blocks 64..512), ms/image; "
              "%GEMM = achieved GFLOP/s over the GEMM rate of the same precision")
        print(f"{'L':>5} {'GFLOP':>6} {'fp32 b32':>9} {'bf16 b32':>9} {'bf16/fp32':>9} {'fp32 b1':>8} {'bf16 b1':>8} "
              f"{'%fp32GEMM':>9} {'%bf16GEMM':>9} {'paper GPU':>9} {'paper/ours':>10}")
        report["fdnet_extraction_ms"] = {}
        for length in lengths:
            t = runtime.fdnet_extraction(vector_length=length, repeats=repeats)
            flops = runtime.content_flops(dataclasses.replace(paper_model, vector_length=length))
            paper = runtime.PAPER_TABLE2.get(length, (float("nan"), float("nan")))[0]
            best = min(t["bf16_batch32"], t["fp32_batch32"])
            share_fp32 = flops / (t["fp32_batch32"] * 1e-3) / 1e9 / gflops
            share_bf16 = flops / (t["bf16_batch32"] * 1e-3) / 1e9 / bf16_gflops
            report["fdnet_extraction_ms"][length] = dict(t, paper_gpu=paper, gflop_per_image=flops / 1e9,
                                                         fraction_of_fp32_gemm=share_fp32,
                                                         fraction_of_bf16_gemm=share_bf16)
            print(f"{length:>5} {flops / 1e9:>6.2f} {t['fp32_batch32']:>9.2f} {t['bf16_batch32']:>9.2f} "
                  f"{t['fp32_batch32'] / t['bf16_batch32']:>8.2f}x {t['fp32_batch1']:>8.2f} {t['bf16_batch1']:>8.2f} "
                  f"{100 * share_fp32:>8.0f}% {100 * share_bf16:>8.0f}% {paper:>9.1f} {paper / best:>9.2f}x")

    workdir = tempfile.TemporaryDirectory(prefix="fdnet-benchmark-")
    try:
        if "api" in parts:
            run_dir, config = runtime.temporary_fdnet_run(workdir.name, "cpu")
            flops = runtime.content_flops(config.model)
            images = _images(args, tuple(config.model.input_size), uint8=True)
            t = runtime.descriptor_paths(run_dir, images, repeats=max(1, repeats - 2), device="cpu",
                                         compiled=args.compile)
            speedup = t["fp32_eager"] / t["extract"]
            rate = flops / (t["extract"] * 1e-3) / 1e9
            reference = bf16_gflops if t["extract_bf16"] else gflops
            report["cpu_preset_descriptor_ms"] = dict(t, gflop_per_image=flops / 1e9, speedup=speedup,
                                                      fraction_of_gemm=rate / reference,
                                                      input_size=list(config.model.input_size),
                                                      vector_length=config.model.vector_length,
                                                      images=len(images))
            print(f"\nFDNet `cpu` preset descriptor through the public API (trunk + encoders, "
                  f"{config.model.input_size[0]}x{config.model.input_size[1]}, L = {config.model.vector_length}, "
                  f"{flops / 1e9:.2f} GFLOP/image), {len(images)} images, CPU, ms/image:")
            print(f"  fp32 eager (float32 images, no autocast)   {t['fp32_eager']:8.2f}")
            print(f"  fdnet extract's path (uint8, {'bf16' if t['extract_bf16'] else 'fp32'})        "
                  f"{t['extract']:8.2f}   {speedup:.2f}x the fp32 eager path, {rate:.1f} GFLOP/s = "
                  f"{100 * rate / reference:.0f}% of the {'bf16' if t['extract_bf16'] else 'fp32'} GEMM rate; "
                  f"paper FDNet_512 on a TITAN X 21.2 ms: {21.2 / t['extract']:.1f}x")
            if "extract_compiled" in t:
                report["cpu_preset_descriptor_ms"]["speedup_compiled"] = t["fp32_eager"] / t["extract_compiled"]
                print(f"  fdnet extract --compile                     {t['extract_compiled']:8.2f}   "
                      f"{t['fp32_eager'] / t['extract_compiled']:.2f}x the fp32 eager path (compiling took "
                      f"{t['compile_seconds']:.0f} s)")

        if "gpu" in parts:
            if device.type == "cuda":
                run_dir, _ = runtime.temporary_fdnet_run(workdir.name, "paper", vector_length=512)
                g = runtime.gpu_figures(device, run_dir, seconds=1.0 if args.quick else 3.0)
                g["gemm_gflops_fp32"] = runtime.gemm_gflops(size=8192, repeats=repeats, device=device)
                g["gemm_gflops_bf16"] = runtime.gemm_gflops(size=8192, repeats=repeats, dtype="bf16", device=device)
                report["gpu"] = g
                print(f"\nGPU {g['name']} ({device}): GEMM 8192^3 fp32 {g['gemm_gflops_fp32'] / 1e3:.1f} TFLOP/s, "
                      f"bf16 {g['gemm_gflops_bf16'] / 1e3:.1f} TFLOP/s; FDNet_512 at 224x224, images/s "
                      "(paper: 1000 / 21.2 ms = 47 images/s on a TITAN X):")
                for key, value in g.items():
                    if key.endswith("_images_per_s"):
                        print(f"  {key[:-len('_images_per_s')]:24s} {value:10.0f}   {value / (1000 / 21.2):8.0f}x the paper")
            else:
                report["gpu"] = None
                print(f"\nGPU: none here (device {device}); GPU figures unmeasured")

        if "matching" in parts:
            map_size = map_sizes[0]
            print(f"\nMatching: best of {map_size} references per query, ms/query")
            print(f"{'L':>5} {'numpy 1q':>9} {'numpy batch':>11} {'faiss flat':>10} {'faiss hnsw':>10} {'paper':>9} "
                  f"{'paper/ours':>10}")
            report["matching_ms"] = {}
            for length in lengths:
                m = runtime.matching_per_query(map_size, length)
                paper = runtime.PAPER_TABLE2.get(length, (float("nan"), float("nan")))[1]
                report["matching_ms"][length] = dict(m, paper_gpu=paper, map_size=map_size)
                print(f"{length:>5} {m['numpy_single']:>9.4f} {m['numpy_batched']:>11.4f} {m['faiss_flat']:>10.4f} "
                      f"{m['faiss_hnsw']:>10.4f} {paper:>9.2f} {paper / m['numpy_single']:>9.1f}x")

        if "methods" in parts:
            methods = [m.strip() for m in args.methods.split(",") if m.strip()]
            methods += [m for m in checkpoints if m not in methods]
            print(f"\nExtraction through the descriptor interface, {args.num_images} images, ms/image "
                  f"(decoding excluded); vs SAD = SAD's time / method's; vs paper = the paper's Table 5 time / ours")
            report["method_extraction_ms"] = {}
            cache = {}
            for method in methods:
                try:
                    descriptor = create(method, checkpoint=checkpoints.get(method), device="cpu")
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
                paper = runtime.PAPER_TABLE5.get(method, (None, None))[0]
                vs_paper = f"  paper {paper:g} ms: {paper / ms:.1f}x" if paper else ""
                print(f"  {method:10s} {ms:9.3f} ms/image  ({descriptor.dim}-d, input {size[0]}x{size[1]}){vs_paper}")
            sad = report["method_extraction_ms"].get("sad")
            for method, ms in report["method_extraction_ms"].items():
                if ms:
                    if sad:
                        report.setdefault("ratio_vs_sad", {})[method] = sad / ms
                    if method in runtime.PAPER_TABLE5:
                        report.setdefault("ratio_vs_paper_table5", {})[method] = runtime.PAPER_TABLE5[method][0] / ms
            report["paper_table5"] = {k: {"extraction_ms": v[0], "matching_ms": v[1]}
                                      for k, v in runtime.PAPER_TABLE5.items()}

        if "scale" in parts:
            dim = args.scale_dim
            if dim is None:
                dim = 512
                if "fdnet" in checkpoints:
                    from fdnet.methods.fdnet.config import TrainConfig
                    from fdnet.runs import load_config

                    dim = int(load_config(checkpoints["fdnet"], TrainConfig).model.vector_length)
            report["scale"] = []

            def log(message: str) -> None:
                print(message, flush=True)

            for n in map_sizes:
                print(f"\nScale: a map of {n:,} random unit {dim}-d vectors, {min(args.queries, n)} queries = map "
                      f"vectors + noise {args.noise}; recall@1 against exact search")
                vectors = runtime.random_map(n, dim)
                queries = runtime.revisit_queries(vectors, args.queries, args.noise)
                report["scale"] += runtime.scale_rows(vectors, queries, kinds, overrides, source="random", log=log,
                                                      sweep=sweep)
                del vectors
            if args.map_vectors:
                vectors = _read_vectors(args.map_vectors, "map vectors")
                queries = (_read_vectors(args.query_vectors, "query vectors") if args.query_vectors
                           else runtime.revisit_queries(vectors, args.queries, args.noise))
                if queries.shape[1] != vectors.shape[1]:
                    raise ConfigError(f"--query-vectors are {queries.shape[1]}-d but --map-vectors "
                                      f"{vectors.shape[1]}-d")
                print(f"\nScale: {args.map_vectors}, {len(vectors):,} real {vectors.shape[1]}-d vectors, "
                      f"{len(queries)} queries")
                report["scale"] += runtime.scale_rows(vectors, queries, kinds, overrides, source=str(args.map_vectors),
                                                      log=log, sweep=sweep)
    finally:
        workdir.cleanup()

    if args.json:
        atomic_write_text(args.json, json.dumps(report, indent=2, default=float))
        print(f"\nwrote {args.json}")
    return 0
