"""`fdnet benchmark` (parses the flags; :mod:`fdnet.performance.benchmark` measures): extraction
ms/image and matching ms/query on this machine, every figure stated against references measured
in the same run (fp32 and bf16 GEMM rates, FDNet's fp32 eager path) and against the paper's
Table 2/5 (TITAN X); GPU figures when a GPU is present; and indexed search on maps of
10^3-10^6 places (``--map-size``). Nothing here is asserted by tests: machines are shared and
noisy, so the command prints ratios measured side by side."""

from __future__ import annotations

from fdnet.performance.benchmark_plan import DEFAULT_INDEXES, DEFAULT_METHODS, PARTS


def register(sub) -> None:
    from fdnet.cli.common import add_device_argument, thread_count

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
    p.add_argument(
        "--threads",
        type=thread_count(),
        default=None,
        help="torch and faiss threads (default: all cores; the report records the count, so give the "
        "same one to compare machines)",
    )
    p.add_argument(
        "--parts",
        default=",".join(PARTS),
        help=f"what to measure, comma-separated from {','.join(PARTS)} (default all; the GEMM "
        "references are always measured)",
    )
    _add_method_arguments(p)
    _add_scale_arguments(p)
    p.add_argument("--quick", action="store_true", help="fewer repeats and only L=512 (for smoke tests)")
    p.add_argument("--json", help="write all figures as JSON")
    add_device_argument(p)
    p.set_defaults(func=run)


def _add_method_arguments(p) -> None:
    """Which methods are timed, on what images and at which FDNet lengths."""
    p.add_argument(
        "--method",
        default=DEFAULT_METHODS,
        help="comma-separated methods to time through the descriptor interface "
        f"(default {DEFAULT_METHODS}); add e.g. fdnet with --checkpoint fdnet:RUN_DIR",
    )
    p.add_argument(
        "--checkpoint",
        action="append",
        default=[],
        metavar="METHOD:RUN_DIR",
        help="checkpoint for a trained method (repeatable)",
    )
    p.add_argument(
        "--weights",
        action="append",
        default=[],
        metavar="METHOD:FILE",
        help="weights file of a method (e.g. onnx:MODEL.onnx to time any ONNX model; repeatable)",
    )
    p.add_argument("--images", help="folder of images to time methods on (default: a synthetic route)")
    p.add_argument("--num-images", type=int, default=32, help="images per method timing (default 32)")
    p.add_argument("--lengths", default="256,512,1024,2048", help="FDNet vector lengths to time")
    p.add_argument(
        "--compile",
        nargs="?",
        const="on",
        choices=("auto", "on", "off"),
        default="auto",
        help="also time `fdnet extract --compile` (torch.compile; compiling takes about a minute): on, "
        "off, or auto (default: as `fdnet extract` decides, on a GPU from its folder size, so here on "
        "only when --num-images reaches it; off on the CPU); a bare --compile means on",
    )


def _add_scale_arguments(p) -> None:
    """The maps of the matching, scale and loop parts: sizes, indexes, queries, vectors."""
    p.add_argument(
        "--map-size",
        default="1000",
        help="map sizes, comma-separated (e.g. 1000,100000,1000000): the first is the matching table's "
        "map; each is a random map of the scale benchmark (default 1000)",
    )
    p.add_argument(
        "--loop-map-size",
        default="10000,100000,1000000",
        help="map sizes of the loop part: the loop-closure detector's ms/frame with exhaustive search "
        "and with the index (default 10000,100000,1000000; --quick: the smallest); a map above "
        "2000000 places is streamed to a file database and decided through compressed codes only",
    )
    p.add_argument(
        "--loop-compressed-size",
        default="",
        help="map sizes of compressed place search in the loop part (codes in memory, vectors in a file "
        "on disk, re-ranked exactly; e.g. 100000,1000000,10000000; default none); needs "
        "--loop-real-vectors; 2 KB of disk per place in the temporary folder",
    )
    p.add_argument(
        "--loop-real-vectors",
        default="",
        metavar="NPZ[,NPZ]",
        help="FDNet vectors the compressed maps are made from (.npz: v, cond = 0 for the reference "
        "traverse and others for the same places seen again, ids = the place of each)",
    )
    p.add_argument(
        "--indexes", default=DEFAULT_INDEXES, help=f"faiss indexes of the scale benchmark (default {DEFAULT_INDEXES})"
    )
    p.add_argument(
        "--index-set",
        action="append",
        default=[],
        metavar="KIND:KEY=VALUE",
        help="an index setting for the scale benchmark, e.g. ivf:ivf_probe=32 (repeatable)",
    )
    p.add_argument(
        "--sweep",
        action="append",
        default=[],
        metavar="KEY=V1,V2,...",
        help="measure each built index at several search-time settings without rebuilding it: "
        "ivf_probe (ivf, ivfpq) or hnsw_ef_search (hnsw), e.g. --sweep ivf_probe=16,32,64",
    )
    p.add_argument("--queries", type=int, default=1000, help="queries per map in the scale benchmark (default 1000)")
    p.add_argument(
        "--noise",
        type=float,
        default=0.5,
        help="norm of the noise added to a map vector to make a query (default 0.5: cosine ~0.9 to " "its place)",
    )
    p.add_argument(
        "--scale-dim",
        type=int,
        help="vector length of the random maps (default: FDNet's, 512, or that of --checkpoint fdnet:RUN)",
    )
    p.add_argument(
        "--map-vectors",
        metavar="FILE",
        help="a real descriptor's vectors for the scale benchmark too: .npy (N, D) or an .npz from "
        "`fdnet extract` (its content array)",
    )
    p.add_argument(
        "--query-vectors",
        metavar="FILE",
        help="queries for --map-vectors (.npy/.npz); default: its vectors plus --noise",
    )


def run(args) -> int:
    import os
    import sys

    from fdnet.cli.extract import compiles
    from fdnet.performance.benchmark import run_benchmark
    from fdnet.performance.benchmark_plan import BenchmarkRequest, plan_benchmark

    command = "fdnet " + " ".join(sys.argv[1:]) if sys.argv and "benchmark" in sys.argv else None
    plan = plan_benchmark(
        BenchmarkRequest(
            parts=args.parts,
            methods=args.method,
            checkpoints=tuple(args.checkpoint),
            map_size=args.map_size,
            indexes=args.indexes,
            index_set=tuple(args.index_set),
            sweep=tuple(args.sweep),
            images=args.images,
            num_images=args.num_images,
            queries=args.queries,
            noise=args.noise,
            scale_dim=args.scale_dim,
            map_vectors=args.map_vectors,
            query_vectors=args.query_vectors,
            lengths=args.lengths,
            compile=compiles(args, args.num_images),
            quick=args.quick,
            threads=args.threads or os.cpu_count() or 1,
            device=args.device,
            command=command,
            loop_map_size=args.loop_map_size,
            weights=tuple(args.weights),
            loop_compressed_size=args.loop_compressed_size,
            loop_real_vectors=args.loop_real_vectors,
        )
    )
    run_benchmark(plan, out=lambda line: print(line, flush=True), json_path=args.json)
    return 0
