"""What ``fdnet benchmark`` is asked to measure: the command's settings as it spells them
(:class:`BenchmarkRequest`), checked and parsed by :func:`plan_benchmark` into a
:class:`BenchmarkPlan` (every refusal before the first measurement), which
:func:`fdnet.performance.benchmark.run_benchmark` carries out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from fdnet.errors import ConfigError, DataError

DEFAULT_METHODS = "raw,sad,hog,gist,dbow,conv3,landmarks"
PARTS = ("fdnet", "api", "gpu", "matching", "methods", "scale", "loop")
DEFAULT_INDEXES = "flat,ivf,ivfpq,hnsw"


@dataclass
class BenchmarkPlan:
    """Checked benchmark settings (see :func:`plan_benchmark`)."""

    parts: list[str]
    methods: list[str]
    checkpoints: dict[str, str]
    map_sizes: list[int]
    kinds: list[str]
    #: map sizes of the loop-closure part (exhaustive search against the index)
    loop_map_sizes: list[int] = field(default_factory=lambda: [10_000, 100_000, 1_000_000])
    #: map sizes of compressed place search (codes in memory, vectors on disk; none by default)
    loop_compressed_sizes: list[int] = field(default_factory=list)
    #: FDNet vectors (.npz: v, cond, ids) the compressed maps are made from
    loop_real_vectors: list[str] = field(default_factory=list)
    overrides: dict = field(default_factory=dict)
    sweep: dict = field(default_factory=dict)
    images: str | None = None
    num_images: int = 32
    queries: int = 1000
    noise: float = 0.5
    scale_dim: int | None = None
    map_vectors: str | None = None
    query_vectors: str | None = None
    lengths: list[int] = field(default_factory=lambda: [256, 512, 1024, 2048])
    compile: bool = False
    quick: bool = False
    threads: int = 2
    device: str = "auto"
    command: str | None = None

    #: weights files by method (``--weights onnx:MODEL.onnx``)
    weights: dict[str, str] = field(default_factory=dict)

    @property
    def repeats(self) -> int:
        return 2 if self.quick else 5


def _comma_list(text: str) -> list[str]:
    return [v.strip() for v in str(text).split(",") if v.strip()]


@dataclass(frozen=True)
class BenchmarkRequest:
    """``fdnet benchmark``'s settings as the command spells them: comma lists (``parts``,
    ``methods``, ``map_size``, ``indexes``, ``lengths``, ``loop_map_size``), ``METHOD:RUN_DIR``
    (``checkpoints``) and ``METHOD:FILE`` (``weights``), ``KIND:KEY=VALUE`` (``index_set``),
    ``KEY=V1,V2`` (``sweep``); :func:`plan_benchmark` checks and parses them."""

    parts: str = ",".join(PARTS)
    methods: str = DEFAULT_METHODS
    checkpoints: tuple = ()
    map_size: str = "1000"
    indexes: str = DEFAULT_INDEXES
    index_set: tuple = ()
    sweep: tuple = ()
    images: str | None = None
    num_images: int = 32
    queries: int = 1000
    noise: float = 0.5
    scale_dim: int | None = None
    map_vectors: str | None = None
    query_vectors: str | None = None
    lengths: str = "256,512,1024,2048"
    compile: bool = False
    quick: bool = False
    threads: int = 2
    device: str = "auto"
    command: str | None = None
    loop_map_size: str = "10000,100000,1000000"
    weights: tuple = ()
    loop_compressed_size: str = ""
    loop_real_vectors: str = ""


def plan_benchmark(request: BenchmarkRequest) -> BenchmarkPlan:
    """Check the command's settings as given (:class:`BenchmarkRequest`) and return them parsed;
    raises ConfigError/DataError naming the flag."""
    from fdnet.matching.index import INDEX_KINDS

    r = request
    parts, map_size, loop_map_size, quick, indexes = r.parts, r.map_size, r.loop_map_size, r.quick, r.indexes
    queries, num_images, threads, noise = r.queries, r.num_images, r.threads, r.noise
    map_vectors, query_vectors, lengths = r.map_vectors, r.query_vectors, r.lengths

    chosen = _comma_list(parts)
    unknown = sorted(set(chosen) - set(PARTS))
    if unknown:
        raise ConfigError(f"--parts: unknown {', '.join(unknown)}; choose from {','.join(PARTS)}")
    try:
        map_sizes = [int(v) for v in _comma_list(map_size)]
    except ValueError as exc:
        raise ConfigError(f"--map-size {map_size!r}: expected whole numbers, e.g. 1000,100000") from exc
    if not map_sizes or min(map_sizes) < 2:
        raise ConfigError(f"--map-size {map_size!r}: every map needs at least 2 places")
    try:
        loop_map_sizes = [int(v) for v in _comma_list(loop_map_size)]
    except ValueError as exc:
        raise ConfigError(f"--loop-map-size {loop_map_size!r}: expected whole numbers, e.g. 10000,100000") from exc
    if not loop_map_sizes or min(loop_map_sizes) < 1:
        raise ConfigError(f"--loop-map-size {loop_map_size!r}: every map needs at least 1 place")
    if quick:
        loop_map_sizes = [min(loop_map_sizes)]
    compressed_sizes, real_vectors = _compressed_maps(r.loop_compressed_size, r.loop_real_vectors)
    kinds = _comma_list(indexes)
    for kind in kinds:
        if kind not in INDEX_KINDS:
            raise ConfigError(f"--indexes: unknown index {kind!r}; choose from {', '.join(INDEX_KINDS)}")
    if queries < 1 or num_images < 1 or threads < 1:
        raise ConfigError("--queries, --num-images and --threads must be at least 1")
    if noise < 0:
        raise ConfigError(f"--noise must be >= 0, got {noise}")
    for flag, path in (("--map-vectors", map_vectors), ("--query-vectors", query_vectors)):
        if path is not None and not Path(path).is_file():
            raise DataError(f"{path}: {flag} file not found")
    if query_vectors and not map_vectors:
        raise ConfigError("--query-vectors needs --map-vectors")
    parsed_checkpoints, parsed_weights = {}, {}
    for flag, items, parsed, what in (
        ("--checkpoint", r.checkpoints, parsed_checkpoints, "RUN_DIR"),
        ("--weights", r.weights, parsed_weights, "FILE"),
    ):
        for item in items:
            if ":" not in item:
                raise ConfigError(f"{flag} {item!r}: expected METHOD:{what}")
            method, path = item.split(":", 1)
            parsed[method.strip()] = path
    try:
        length_list = [int(v) for v in _comma_list(lengths)]
    except ValueError as exc:
        raise ConfigError(f"--lengths {lengths!r}: expected whole numbers, e.g. 256,512") from exc
    from fdnet.backbones import check_device_spec

    return BenchmarkPlan(
        parts=chosen,
        methods=_comma_list(r.methods),
        checkpoints=parsed_checkpoints,
        weights=parsed_weights,
        map_sizes=map_sizes,
        loop_map_sizes=loop_map_sizes,
        kinds=kinds,
        overrides=index_overrides(r.index_set),
        sweep=sweeps(r.sweep),
        images=r.images,
        num_images=num_images,
        queries=queries,
        noise=noise,
        scale_dim=r.scale_dim,
        map_vectors=map_vectors,
        query_vectors=query_vectors,
        lengths=length_list,
        compile=r.compile,
        quick=quick,
        threads=threads,
        device=check_device_spec(r.device),
        command=r.command,
        loop_compressed_sizes=compressed_sizes,
        loop_real_vectors=real_vectors,
    )


def _compressed_maps(sizes: str, vectors: str) -> tuple[list[int], list[str]]:
    """``--loop-compressed-size`` and ``--loop-real-vectors``, checked."""
    try:
        parsed = [int(v) for v in _comma_list(sizes)]
    except ValueError as exc:
        raise ConfigError(f"--loop-compressed-size {sizes!r}: expected whole numbers, e.g. 100000,1000000") from exc
    files = _comma_list(vectors)
    if parsed and min(parsed) < 10_000:
        raise ConfigError(f"--loop-compressed-size {sizes!r}: compressed maps start at 10000 places")
    if parsed and not files:
        raise ConfigError("--loop-compressed-size needs --loop-real-vectors (FDNet vectors, .npz with v, cond, ids)")
    for path in files:
        if not Path(path).is_file():
            raise DataError(f"{path}: --loop-real-vectors file not found")
    return parsed, files


def index_overrides(items) -> dict:
    """``KIND:KEY=VALUE`` items -> {kind: {key: value}} (checked by the index's settings)."""
    from fdnet.matching.index import INDEX_KINDS, parse_index_settings

    out: dict = {}
    for item in items:
        kind, sep, pair = item.partition(":")
        if not sep or kind not in INDEX_KINDS:
            raise ConfigError(
                f"--index-set {item!r}: expected KIND:KEY=VALUE with KIND one of " f"{', '.join(INDEX_KINDS)}"
            )
        settings = parse_index_settings(kind, [pair], where="--index-set")
        key = pair.split("=", 1)[0].strip()
        out.setdefault(kind, {})[key] = getattr(settings, key)
    return out


def sweeps(items) -> dict:
    """``KEY=V1,V2,...`` items -> {key: [values]} for the search-time settings that can be swept."""
    from fdnet.performance.timing import SWEEPABLE

    out = {}
    for item in items:
        key, sep, values = item.partition("=")
        key = key.strip()
        try:
            numbers = [int(v) for v in values.split(",") if v.strip()]
        except ValueError:
            numbers = []
        if not sep or key not in SWEEPABLE or not numbers or min(numbers) < 1:
            raise ConfigError(
                f"--sweep {item!r}: expected KEY=V1,V2,... with KEY one of {', '.join(SWEEPABLE)} "
                "and whole numbers >= 1"
            )
        out[key] = numbers
    return out
