"""Indexed nearest-neighbour search with faiss, for maps of up to millions of places.

Only for descriptors whose similarity is a dot product (``dot_product_similarity``); others
(SAD, DBoW's L1 score, Landmarks) raise a clear error rather than silently ranking by the
wrong measure.

Kinds (``IndexSettings.kind``), all by inner product (cosine for unit vectors):

``flat``
    exact: every query against every vector, blocked BLAS (faiss ``IndexFlatIP``). Memory
    4 * dim bytes per place; time grows with the map.
``ivf``
    IVF-Flat: k-means cells (``ivf_lists``, default about sqrt(N)); a query scans the
    ``ivf_probe`` (default 32) nearest cells. Same memory as flat, a fraction of its time; needs training
    (k-means on up to ``train_points`` of the vectors, done when the index is first searched or
    :meth:`VectorIndex.build` is called).
``ivfpq``
    IVF-PQ: cells as ``ivf``, each vector compressed to ``pq_bytes`` bytes (product quantisation,
    8 bits per sub-vector, fewer below 9,984 vectors: :func:`pq_bits_for`; default dim / 8).
    Memory ~pq_bytes + 8 bytes per place; scores are approximate, ``refine`` > 0 re-ranks
    ``refine`` x k candidates by exact dot products (which keeps the full vectors too).
``hnsw``
    HNSW graph (``hnsw_neighbors`` links per node, ``hnsw_ef_construction`` / ``hnsw_ef_search``
    beam widths). No training, fast queries, the slowest to build; memory 4 * dim + ~8 *
    hnsw_neighbors bytes per place.

An index is built once and saved (:meth:`VectorIndex.save`) as one file: a fixed magic, a JSON
header (kind, settings, dim, count and whatever the caller adds, e.g. a database's data
version), then faiss's own serialisation (``faiss.write_index``, streamed). :meth:`VectorIndex.load`
reads it back with ``faiss.read_index``: no pickle anywhere. Search-time settings
(``ivf_probe``, ``hnsw_ef_search``, ``refine``) may differ at load time; build-time ones come
from the file.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from fdnet.errors import ConfigError, DataError

INDEX_KINDS = ("flat", "hnsw", "ivf", "ivfpq")
#: settings that only affect searching: may be changed on a saved index
SEARCH_SETTINGS = ("hnsw_ef_search", "ivf_probe", "refine", "compressed_from")
MAGIC = b"FDNETIDX"
FORMAT_VERSION = 1


@dataclass
class IndexSettings:
    #: flat = exact inner product; hnsw = graph (no training, fast, approximate);
    #: ivf = inverted lists (IVF-Flat, needs training); ivfpq = inverted lists of PQ codes
    kind: str = "flat"
    hnsw_neighbors: int = 32
    hnsw_ef_search: int = 128
    #: beam width while building the graph (faiss's default 40)
    hnsw_ef_construction: int = 40
    ivf_lists: int = 0  # 0 = about 4*sqrt(N) up to 10^4 places, sqrt(N) beyond (see ivf_lists_for)
    #: cells scanned per query (32: recall@1 0.985 against exact search on 10^6 random 512-d vectors,
    #: docs/performance.md; 16: 0.942)
    ivf_probe: int = 32
    #: ivfpq: bytes (8-bit sub-quantizers) per vector; 0 = dim / 8; must divide dim
    pq_bytes: int = 0
    #: ivfpq: re-rank refine x k candidates by exact dot product (0 = no re-ranking)
    refine: int = 0
    #: ivf/ivfpq: vectors k-means is trained on (0 = up to 64 per list, at least 39, all if fewer)
    train_points: int = 0
    #: a place database (a file, dot-product vectors) of at least this many places keeps its
    #: vectors in a file beside it and is searched through compressed codes instead of this
    #: index (:mod:`fdnet.matching.database.vector_store`; never below 4096 places)
    compressed_from: int = 2_000_000


def ivf_lists_for(count: int, settings: IndexSettings) -> int:
    """Cells for ``count`` vectors: ``ivf_lists`` when set; else 4*sqrt(N) for maps up to 10^4
    (faiss's guideline) and sqrt(N) beyond (k-means over 4*sqrt(N) cells of 10^6 vectors would take
    many minutes on a small machine; sqrt(N) cells with 32 probes gave recall@1 0.985 at 10^6,
    docs/performance.md). Never more than N / 39: faiss's k-means wants 39 points per cell."""
    if settings.ivf_lists:
        lists = settings.ivf_lists
    elif count <= 10_000:
        lists = int(4 * np.sqrt(max(count, 1)))
    else:
        lists = int(np.sqrt(count))
    return max(1, min(lists, count // 39))


def pq_bits_for(count: int) -> int:
    """Bits per PQ sub-vector code: 8 (256 centroids, faiss's usual) once there are 39 training
    points per centroid (9,984 vectors); fewer for smaller maps, which could not train 256."""
    if count >= 39 * 256:
        return 8
    return int(max(1, min(8, np.floor(np.log2(max(count, 2) / 39)))))


def check_settings(settings: IndexSettings, where: str = "index settings", error: type = ConfigError) -> IndexSettings:
    if not isinstance(settings.kind, str) or settings.kind not in INDEX_KINDS:
        raise error(f"{where}: unknown index kind {settings.kind!r}; choose from {', '.join(INDEX_KINDS)}")
    for f in fields(IndexSettings):
        if f.name == "kind":
            continue
        value = getattr(settings, f.name)
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise error(f"{where}: index setting {f.name} must be a non-negative integer, got {value!r}")
    if settings.kind == "hnsw" and settings.hnsw_neighbors < 2:
        raise error(f"{where}: hnsw_neighbors must be at least 2, got {settings.hnsw_neighbors}")
    return settings


def parse_index_settings(kind: str, pairs: list[str] | None = None, where: str = "--index-set") -> IndexSettings:
    """``--index KIND`` plus ``--index-set key=value`` flags -> checked :class:`IndexSettings`."""
    known = {f.name for f in fields(IndexSettings)}
    values: dict = {"kind": kind}
    for pair in pairs or []:
        key, sep, value = str(pair).partition("=")
        key = key.strip()
        if not sep or key not in known or key == "kind":
            raise ConfigError(
                f"{where} {pair!r}: expected KEY=VALUE with KEY one of " f"{', '.join(sorted(known - {'kind'}))}"
            )
        try:
            values[key] = int(value)
        except ValueError as exc:
            raise ConfigError(f"{where} {pair!r}: {key} must be a whole number") from exc
    return check_settings(IndexSettings(**values), where)


def serialised_bytes(index) -> int:
    """Size of a faiss index as faiss serialises it: its vectors or codes, cells and links, i.e.
    about what it holds in memory (counted as written, without making a copy)."""
    import faiss

    counter = [0]

    def count(data) -> int:
        counter[0] += len(data)
        return len(data)

    writer = faiss.PyCallbackIOWriter(count)
    faiss.write_index(index, writer)
    del writer
    return counter[0]


class one_faiss_thread:
    """faiss on one thread within the block: for one frame's add and search, OpenMP's start and
    barrier cost more than a single vector's work (7 ms against well under 1 ms on 2 shared
    cores), and a graph built on one thread is the same graph every time."""

    def __enter__(self):
        import faiss

        self._faiss = faiss
        self._threads = faiss.omp_get_max_threads()
        faiss.omp_set_num_threads(1)

    def __exit__(self, *exc):
        self._faiss.omp_set_num_threads(self._threads)


class VectorIndex:
    """Inner-product index over (N, D) float32 vectors (cosine for unit vectors)."""

    def __init__(self, dim: int, settings: IndexSettings | None = None):
        import faiss

        self.settings = check_settings(settings or IndexSettings())
        self.dim = int(dim)
        self._faiss = faiss
        self._index = None
        self._pending: list[np.ndarray] = []
        if self.settings.kind == "flat":
            self._index = faiss.IndexFlatIP(self.dim)
        elif self.settings.kind == "hnsw":
            self._index = faiss.IndexHNSWFlat(self.dim, self.settings.hnsw_neighbors, faiss.METRIC_INNER_PRODUCT)
            self._index.hnsw.efConstruction = max(1, self.settings.hnsw_ef_construction)
            self._index.hnsw.efSearch = max(1, self.settings.hnsw_ef_search)
        elif self.settings.kind == "ivfpq":
            bytes_ = self.settings.pq_bytes or max(1, self.dim // 8)
            if self.dim % bytes_:
                raise ConfigError(f"index setting pq_bytes={bytes_} must divide the vector length {self.dim}")

    @property
    def trainable(self) -> bool:
        return self.settings.kind in ("ivf", "ivfpq")

    @property
    def is_built(self) -> bool:
        """False while an IVF index still waits for its training data (see :meth:`build`)."""
        return self._index is not None and not self._pending

    def __len__(self) -> int:
        built = self._index.ntotal if self._index is not None else 0
        return built + sum(len(p) for p in self._pending)

    def _check(self, vectors: np.ndarray) -> np.ndarray:
        v = np.ascontiguousarray(np.asarray(vectors, dtype=np.float32))
        if v.ndim != 2 or v.shape[1] != self.dim:
            raise ConfigError(f"index holds {self.dim}-d vectors, got an array of shape {v.shape}")
        return v

    def add(self, vectors: np.ndarray) -> None:
        v = self._check(vectors)
        if self.trainable and self._index is None:
            # IVF needs training data; defer until the first search (or build()).
            self._pending.append(v)
            return
        self._index.add(v)

    def build(self) -> None:
        """Train an IVF index on the vectors added so far and add them (a no-op for the other
        kinds, and once built). Later ``add`` calls go straight into the trained cells."""
        if not self.trainable or self._index is not None:
            return
        faiss = self._faiss
        count = sum(len(p) for p in self._pending)
        lists = ivf_lists_for(count, self.settings)
        quantizer = faiss.IndexFlatIP(self.dim)
        if self.settings.kind == "ivf":
            index = faiss.IndexIVFFlat(quantizer, self.dim, lists, faiss.METRIC_INNER_PRODUCT)
        else:
            if count < 2:
                raise ConfigError(f"an ivfpq index needs at least 2 vectors to train, got {count}")
            bytes_ = self.settings.pq_bytes or max(1, self.dim // 8)
            index = faiss.IndexIVFPQ(quantizer, self.dim, lists, bytes_, pq_bits_for(count), faiss.METRIC_INNER_PRODUCT)
        # faiss's k-means wants >= 39 points per centroid: per cell, and per PQ code (256 of them)
        wanted = self.settings.train_points or max(64 * lists, 39 * 256 if self.settings.kind == "ivfpq" else 0)
        if count:
            index.train(self._sample(min(count, wanted)))
        index.nprobe = max(1, min(self.settings.ivf_probe, lists))
        pending, self._pending = self._pending, []
        final = index
        if self.settings.kind == "ivfpq" and self.settings.refine:
            final = faiss.IndexRefineFlat(index)
            final.k_factor = float(self.settings.refine)
        self._index = final
        while pending:
            self._index.add(pending.pop(0))  # chunk by chunk, releasing each

    def _sample(self, n: int) -> np.ndarray:
        """``n`` of the pending vectors, evenly spread (deterministic)."""
        count = sum(len(p) for p in self._pending)
        if n >= count:
            return np.concatenate(self._pending) if len(self._pending) > 1 else self._pending[0]
        wanted = np.linspace(0, count - 1, n).astype(np.int64)
        out = np.empty((n, self.dim), dtype=np.float32)
        offset, filled = 0, 0
        for chunk in self._pending:
            mine = wanted[(wanted >= offset) & (wanted < offset + len(chunk))] - offset
            out[filled : filled + len(mine)] = chunk[mine]
            filled += len(mine)
            offset += len(chunk)
        return out

    def _apply_search_settings(self) -> None:
        faiss = self._faiss
        index = self._index
        if isinstance(index, faiss.IndexRefineFlat):
            index.k_factor = float(max(1, self.settings.refine))
            index = faiss.downcast_index(index.base_index)
        if isinstance(index, faiss.IndexHNSW):
            index.hnsw.efSearch = max(1, self.settings.hnsw_ef_search)
        elif isinstance(index, faiss.IndexIVF):
            index.nprobe = max(1, min(self.settings.ivf_probe, index.nlist))

    def set_search(self, **values) -> None:
        """Change search-time settings (``ivf_probe``, ``hnsw_ef_search``, ``refine``) of a built
        or loaded index, without rebuilding it."""
        import dataclasses

        for key in values:
            if key not in SEARCH_SETTINGS:
                raise ConfigError(
                    f"{key} is fixed when the index is built; only {', '.join(SEARCH_SETTINGS)} "
                    "can change on a built index"
                )
        self.settings = check_settings(dataclasses.replace(self.settings, **values))
        if self._index is not None:
            self._apply_search_settings()

    def search(self, queries: np.ndarray, k: int, below: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Best ``k`` per query: (indices (Q, k) int64, scores (Q, k) float32); -1 where fewer exist.
        ``below``: only among the vectors added before that index (a flat or IVF index)."""
        self.build()
        q = self._check(queries)
        if len(self) == 0:
            raise ConfigError("the index is empty: add reference vectors before searching")
        k = int(min(k, len(self)))
        if below is None or below >= len(self):
            scores, indices = self._index.search(q, k)
        else:
            scores, indices = self._index.search(q, k, params=self._below(int(below)))
        return indices.astype(np.int64), scores.astype(np.float32)

    def _below(self, below: int):
        """faiss search parameters keeping the ids under ``below`` (with the index's own probe)."""
        faiss, index = self._faiss, self._index
        selector = faiss.IDSelectorRange(0, max(below, 0))
        if isinstance(index, faiss.IndexIVF):
            params = faiss.SearchParametersIVF(sel=selector, nprobe=index.nprobe)
        elif isinstance(index, faiss.IndexFlat):
            params = faiss.SearchParameters(sel=selector)
        else:
            raise ConfigError(f"a {self.settings.kind} index cannot search a prefix of its vectors (flat or ivf can)")
        params.keep_alive = selector  # the parameters hold a raw pointer to it
        return params

    def reconstruct_all(self) -> np.ndarray:
        """All stored vectors in insertion order (exact for flat, hnsw and ivf; ivfpq without
        ``refine`` gives its compressed approximation)."""
        self.build()
        n = self._index.ntotal
        if n == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        faiss = self._faiss
        index = self._index
        if isinstance(index, faiss.IndexRefineFlat):
            return np.asarray(faiss.downcast_index(index.refine_index).reconstruct_n(0, n), dtype=np.float32)
        if isinstance(index, faiss.IndexIVF):
            index.make_direct_map()
        return np.asarray(index.reconstruct_n(0, n), dtype=np.float32)

    def memory_bytes(self) -> int:
        """Size of the index as faiss serialises it: its vectors/codes, cells and links, i.e.
        about what it holds in memory (counted as written, without making a copy)."""
        self.build()
        return serialised_bytes(self._index)

    def describe(self) -> dict:
        """Kind, settings and the parameters faiss chose (cells, bytes per vector)."""
        out = {"kind": self.settings.kind, "dim": self.dim, "count": len(self), "settings": asdict(self.settings)}
        if self._index is not None:
            faiss = self._faiss
            index = self._index
            if isinstance(index, faiss.IndexRefineFlat):
                index = faiss.downcast_index(index.base_index)
            if isinstance(index, faiss.IndexIVF):
                out["ivf_lists"] = int(index.nlist)
            if isinstance(index, faiss.IndexIVFPQ):
                out["pq_bytes"] = int(index.pq.M)
                out["pq_bits"] = int(index.pq.nbits)
        return out

    # ------------------------------------------------------------------ saving and loading
    def save(self, path: str | os.PathLike, metadata: dict | None = None) -> None:
        """Write the index to ``path`` atomically (one file, see the module docstring); an IVF
        index is built first. ``metadata`` (JSON-able) is stored in the header and returned by
        :meth:`read_header`."""
        from fdnet.io import atomic_path

        self.build()
        header = {
            "format": FORMAT_VERSION,
            "kind": self.settings.kind,
            "dim": self.dim,
            "count": len(self),
            "settings": asdict(self.settings),
            "metadata": metadata or {},
        }
        data = json.dumps(header, sort_keys=True).encode()
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(MAGIC)
                fh.write(len(data).to_bytes(8, "little"))
                fh.write(data)
                writer = self._faiss.PyCallbackIOWriter(fh.write)
                self._faiss.write_index(self._index, writer)
                del writer

    @staticmethod
    def read_header(path: str | os.PathLike) -> dict:
        """The JSON header of a saved index (kind, dim, count, settings, metadata), without
        reading the index itself."""
        path = Path(path)
        try:
            with open(path, "rb") as fh:
                return _read_header(fh, path)
        except FileNotFoundError as exc:
            raise DataError(f"{path}: index file not found") from exc
        except OSError as exc:
            raise DataError(f"{path}: cannot read the index file ({exc.strerror or exc})") from exc

    @classmethod
    def load(cls, path: str | os.PathLike, search: dict | None = None) -> "VectorIndex":
        """Read an index written by :meth:`save`. ``search`` overrides search-time settings
        (``ivf_probe``, ``hnsw_ef_search``, ``refine``)."""
        import faiss

        path = Path(path)
        try:
            with open(path, "rb") as fh:
                header = _read_header(fh, path)
                try:
                    reader = faiss.PyCallbackIOReader(fh.read)
                    index = faiss.read_index(reader)
                    del reader
                except RuntimeError as exc:
                    raise DataError(f"{path}: the faiss index in this file cannot be read ({exc})") from exc
        except FileNotFoundError as exc:
            raise DataError(f"{path}: index file not found") from exc
        except OSError as exc:
            raise DataError(f"{path}: cannot read the index file ({exc.strerror or exc})") from exc
        values = dict(header["settings"])
        for key, value in (search or {}).items():
            if key not in SEARCH_SETTINGS:
                raise ConfigError(
                    f"{path}: {key} is fixed when the index is built; only "
                    f"{', '.join(SEARCH_SETTINGS)} can change on a saved index"
                )
            values[key] = value
        known = {f.name for f in fields(IndexSettings)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise DataError(f"{path}: unknown index setting(s) {', '.join(unknown)} (written by a newer fdnet?)")
        settings = check_settings(IndexSettings(**values), f"{path}", DataError)
        out = cls.__new__(cls)
        out.settings, out.dim, out._faiss, out._pending = settings, int(header["dim"]), faiss, []
        out._index = index
        if index.d != out.dim or index.ntotal != int(header["count"]):
            raise DataError(
                f"{path}: the index holds {index.ntotal} {index.d}-d vectors, its header says "
                f"{header['count']} {header['dim']}-d; the file is damaged"
            )
        out._apply_search_settings()
        return out


def _read_header(fh, path: Path) -> dict:
    if fh.read(len(MAGIC)) != MAGIC:
        raise DataError(f"{path}: not an fdnet index file (written by VectorIndex.save / --save-index)")
    size = int.from_bytes(fh.read(8), "little")
    if not 0 < size < 1 << 26:
        raise DataError(f"{path}: damaged index header (length {size})")
    try:
        header = json.loads(fh.read(size))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: damaged index header ({exc})") from exc
    if not isinstance(header, dict) or header.get("format") != FORMAT_VERSION:
        raise DataError(
            f"{path}: index format {header.get('format') if isinstance(header, dict) else '?'} "
            f"is not {FORMAT_VERSION}"
        )
    for key in ("kind", "dim", "count", "settings"):
        if key not in header:
            raise DataError(f"{path}: index header lacks {key!r}")
    return header
