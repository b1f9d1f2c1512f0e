"""Places compressed in memory, exact answers on top: for maps too large to hold as float32.

A map of N places of D floats costs 4 * D * N bytes in memory (2 GB at 10^6 places of 512
floats). Two pieces keep it to a few tens of bytes per place:

:class:`VectorFile`
    the float32 vectors on disk, one file of rows (row i at byte 4 * D * i, no header),
    append-only. Whoever owns the file records how many rows are committed (a place database:
    in the same transaction as the places); an add killed before that commit leaves the file
    longer than the committed count, and opening it with that count cuts the rest off, so the
    file is the old state again and a resumed run appends the same rows. Opened ``read_only``
    it reads the committed rows and cuts nothing (a reader needs no write lock).
:class:`CompressedIndex`
    two codes per place in memory, both in an OPQ rotation of the vectors (learned so that
    product quantisation loses the least; inner products are unchanged by it): faiss IVF-PQ
    fast-scan codes (4-bit, ``pq_subvectors`` / 2 bytes a place, plus its id in its cell's list)
    and finer 8-bit PQ codes (``refine_subvectors`` bytes a place). A query scans ``probe``
    cells of fast-scan codes (by default one cell: every code) for ``candidates`` places,
    re-ranks them by the 8-bit codes to a short list of ``shortlist`` places, and re-ranks those
    by exact dot products with their float vectors read from the file. The scores returned are
    exact; only a place outside the short list can be missed. Places are added as they come (one
    a frame); the rotation, cells and codebooks are trained on the first places and trained
    again (every code re-encoded, read from the file in chunks) when the map has grown
    ``retrain_growth``-fold since, from an evenly spaced sample with faiss's fixed seeds, so the
    same map gives the same index and a resumed run replays the same answers. With cells
    (``lists`` 0: about sqrt(N)), from :data:`HNSW_LISTS` of them (about 4 x 10^6 places) a
    place's cell is found through an HNSW graph over the cells' centroids instead of by
    comparing it with each of them, which is most of the time of encoding a large map.

Why two codes: on the benchmark's maps (real FDNet vectors among distractors drawn from their
Gaussian) the best place wins by 0.01-0.02 of a cosine. 4-bit codes alone (no rotation, 64 of
about sqrt(N) cells scanned, a 256-place short list) missed the exhaustive best place for 35 %
of the queries at 10^6 places; in the OPQ rotation, over every code, they put the exhaustive
best two in a 4096-place fast-scan list for 99 % of them, and the 8-bit codes rank that list
well enough that both stay among the 64 re-ranked exactly (docs/performance.md, *Compressed
places*).
"""

from __future__ import annotations

import dataclasses
import math
import mmap
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fdnet.errors import ConfigError, DataError
from fdnet.matching.index import IndexSettings, ivf_lists_for, one_faiss_thread, pq_bits_for, serialised_bytes

#: rows read from the vector file per chunk while (re-)encoding the map
CHUNK_ROWS = 65_536
#: threads reading a short list's rows from the vector file
READERS = 16
#: from this many separate runs of rows a read is shared among the threads
THREADED_RUNS = 256
_READERS: list = []


def _readers():
    """The thread pool that reads rows (made on first use, shared)."""
    if not _READERS:
        from concurrent.futures import ThreadPoolExecutor

        _READERS.append(ThreadPoolExecutor(READERS, thread_name_prefix="fdnet-vector-file"))
    return _READERS[0]


#: from this many inverted lists the cells are found through an HNSW graph over their centroids
HNSW_LISTS = 2048


class VectorFile:
    """Append-only float32 rows in ``path`` (see the module docstring), with
    :class:`~fdnet.matching.place_map.GrowingArray`'s interface (``len``, ``append``,
    ``extend``, ``truncate``, ``view``). ``committed``: the rows the owner recorded as stored;
    longer files are cut to it (an add that was killed), shorter ones are refused (the file was
    damaged or replaced). None: every whole row in the file counts. ``read_only``: the file must
    exist, rows past the committed count (an add in progress or killed) are left alone and
    unread, and writing is refused."""

    def __init__(self, path: str | os.PathLike, dim: int, committed: int | None = None, read_only: bool = False):
        self.path = Path(path)
        self.dim = int(dim)
        self.read_only = bool(read_only)
        self._row = 4 * self.dim
        try:
            self._fd = os.open(self.path, os.O_RDONLY if self.read_only else os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise DataError(f"{self.path}: cannot open the vector file ({exc.strerror or exc})") from exc
        size = os.fstat(self._fd).st_size
        whole = size // self._row
        if committed is not None and whole < int(committed):
            os.close(self._fd)
            raise DataError(
                f"{self.path}: holds {whole} vectors, its database committed {committed}; the vector "
                "file was damaged or replaced"
            )
        self._count = whole if committed is None else int(committed)
        if size != self._count * self._row and not self.read_only:
            os.ftruncate(self._fd, self._count * self._row)  # a killed add's rows: the old state again
            os.fsync(self._fd)
        self._map: np.ndarray | None = None

    def __len__(self) -> int:
        return self._count

    def append(self, row) -> None:
        self.extend(np.asarray(row, np.float32)[None])

    def _writable(self) -> None:
        if self.read_only:
            raise ConfigError(f"{self.path}: the vector file was opened read-only")

    def extend(self, rows: np.ndarray) -> None:
        self._writable()
        rows = np.ascontiguousarray(rows, dtype=np.float32)
        if rows.ndim != 2 or rows.shape[1] != self.dim:
            raise ConfigError(f"{self.path}: holds {self.dim}-d vectors, got an array of shape {rows.shape}")
        data = rows.tobytes()
        offset, written = self._count * self._row, 0
        while written < len(data):  # pwrite may write less than asked (a signal, a full disk)
            try:
                done = os.pwrite(self._fd, data[written:], offset + written)
            except OSError as exc:  # the rows counted so far stay; what was written past them is cut on open
                raise DataError(f"{self.path}: cannot write vectors ({exc.strerror or exc})") from exc
            if done <= 0:
                raise DataError(f"{self.path}: cannot write vectors (disk full?)")
            written += done
        self._count += len(rows)

    def sync(self) -> None:
        """Make the rows written so far durable (before the owner commits their count)."""
        self._writable()
        os.fsync(self._fd)

    def truncate(self, count: int) -> None:
        """Forget the rows from ``count`` on (the file is cut too)."""
        self._writable()
        self._count = min(int(count), self._count)
        os.ftruncate(self._fd, self._count * self._row)
        self._map = None

    def view(self, count: int | None = None) -> np.ndarray:
        """The first ``count`` rows (default all) as a read-only memory map: reading a row reads
        the file (through the page cache), nothing is copied into memory."""
        count = self._count if count is None else min(int(count), self._count)
        if self._map is None or len(self._map) < count:
            self._map = None
            if count == 0:
                return np.zeros((0, self.dim), np.float32)
            # a new map when the file grew past the old one (one mmap call, nothing read); no
            # read-ahead: the rows a query reads are scattered, and pages read ahead around each
            # would stay mapped (resident) without being used
            mapped = mmap.mmap(self._fd, self._count * self._row, prot=mmap.PROT_READ)
            mapped.madvise(mmap.MADV_RANDOM)
            self._map = np.frombuffer(mapped, np.float32).reshape(self._count, self.dim)
        return self._map[:count]

    def read(self, start: int, stop: int) -> np.ndarray:
        """Rows ``start`` to ``stop`` copied into memory, read with ``pread`` (a streamed pass over
        the file, e.g. encoding it, leaves no mapped pages behind)."""
        stop = min(int(stop), self._count)
        data = os.pread(self._fd, max(0, stop - start) * self._row, start * self._row)
        return np.frombuffer(data, np.float32).reshape(-1, self.dim).copy()

    def rows(self, ids: np.ndarray) -> np.ndarray:
        """The rows at ``ids`` (any order, repeats allowed) copied into memory, read with ``pread``:
        a query's short list is scattered over the file, and reading it through a memory map
        would leave the pages around each row mapped (the kernel maps cached neighbours with each
        fault), so the process's resident memory would grow towards the file's size. Ids that
        follow each other in the file (a sequence's places, the recent past) are one read each
        run; a few runs are read in this thread (from the page cache a read costs microseconds,
        and handing it to a thread costs more), many by :data:`READERS` threads (rows not in the
        page cache are disk reads: several in flight, 2.4x faster on an SSD)."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        out = np.empty((len(ids), self.dim), np.float32)
        if not len(ids):
            return out
        if ids.min() < 0 or ids.max() >= self._count:
            raise ConfigError(f"{self.path}: row ids must be below {self._count}")
        wanted, where = np.unique(ids, return_inverse=True)
        in_order = len(wanted) == len(ids) and bool(np.all(wanted == ids))
        rows = out if in_order else np.empty((len(wanted), self.dim), np.float32)
        starts = np.flatnonzero(np.diff(wanted, prepend=-2) != 1)  # a run: consecutive ids
        stops = np.append(starts[1:], len(wanted))

        def read(runs: np.ndarray) -> int:
            done = 0
            for a, b in zip(starts[runs].tolist(), stops[runs].tolist()):
                buffer, offset = memoryview(rows[a:b]).cast("B"), int(wanted[a]) * self._row
                while buffer:  # one call reads at most about 2 GB (Linux), or less when interrupted
                    got = os.preadv(self._fd, [buffer], offset)
                    if got <= 0:
                        break  # the file ends early: counted below
                    buffer, offset, done = buffer[got:], offset + got, done + got
            return done

        runs = np.arange(len(starts))
        if len(runs) <= THREADED_RUNS:
            done = read(runs)
        else:
            done = sum(_readers().map(read, np.array_split(runs, READERS)))
        if done != len(wanted) * self._row:
            raise DataError(f"{self.path}: the vector file is shorter than its {self._count} rows")
        if not in_order:  # read in file order, once each: back to the order asked for
            out[:] = rows[where.reshape(-1)]
        return out

    def close(self) -> None:
        self._map = None
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> "VectorFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class CompressedSettings:
    #: 4-bit sub-quantizers per vector (bytes per code: half this), even, dividing the vector
    #: length; 0: dim / 8 (64 for 512 floats: 32 bytes a place), or the nearest even divisor below
    pq_subvectors: int = 0
    #: 8-bit sub-quantizers of the second, finer code (its bytes a place), dividing the vector
    #: length; 0: dim / 4 (128 for 512 floats), or the nearest divisor below
    refine_subvectors: int = 0
    #: inverted lists: 1 (the default) scans every code, one list of residuals from the map's
    #: mean; 0: about sqrt(N), as :func:`~fdnet.matching.index.ivf_lists_for`. On the benchmark's
    #: maps the exhaustive best two lie in the scanned cells only when about 70 % of them are
    #: scanned, and scanning 70 % of sqrt(N) lists costs more than scanning one list of all codes
    #: (faiss's fast-scan works list by list; a whole query at 2 x 10^5 places: 0.070 against
    #: 0.057 x the exhaustive GEMV); a map whose places cluster may gain from cells, fewer probed
    lists: int = 1
    #: lists scanned per query (0: :data:`PROBE_SHARE` of them)
    probe: int = 0
    #: places the fast-scan codes propose per query, re-ranked by the 8-bit codes (0: by the
    #: map's size, :func:`candidates_for`)
    candidates: int = 0
    #: places re-ranked exactly per query (at least k), read from the vector file
    shortlist: int = 64
    #: learn an OPQ rotation before quantising (False: the vectors as they are)
    rotate: bool = True
    #: train the cells and codebooks again when the map has grown this many times since
    retrain_growth: int = 4
    #: vectors the training samples (0: 64 per list, at least 39 x 256 for the 8-bit codebooks)
    train_points: int = 0


#: the settings that change what the trained codes are (the others only how a search runs)
_BUILD_SETTINGS = ("pq_subvectors", "refine_subvectors", "lists", "rotate", "retrain_growth", "train_points")

#: share of the cells scanned when ``probe`` is 0: distractors without cluster structure (the
#: benchmark's) need about this many for the exhaustive best two to lie in the scanned cells
PROBE_SHARE = 0.7
# Training on one thread: the rotation and the codebooks are trained on one thread. Their k-means runs many
# short parallel steps, and on a machine whose cores are busy with other work OpenMP's threads
# wait for each other at every step: 30-50x slower on two threads than on one, measured on
# the 2 loaded cores of the benchmark's machine. Only the k-means of an HNSW-path map's many
# cells (long steps, CompressedIndex._cells) and encoding keep every thread.

#: OPQ's iterations (faiss's default is 50: a fifth of the time, nearly the same rotation) and
#: the most points it learns from
OPQ_ITERATIONS = 10
OPQ_POINTS = 20_000


def pq_subvectors_for(dim: int) -> int:
    """The largest even divisor of ``dim`` up to dim / 8 (at least 2; 2 for an odd ``dim`` is
    refused by :func:`check_compressed`)."""
    for m in range(max(2, dim // 8), 1, -1):
        if m % 2 == 0 and dim % m == 0:
            return m
    return 2


#: fast-scan candidates per query up to 10^6 places (:func:`candidates_for`)
CANDIDATES = 4096


def candidates_for(settings: CompressedSettings, count: int) -> int:
    """Places the fast-scan codes propose per query over a map of ``count``: ``candidates``, or
    when it is 0 :data:`CANDIDATES`, doubled for each tenfold growth of the map past 10^6 (in
    1024s). A fixed count is a smaller share of a larger map: at 10^7 places of the benchmark's
    map, 4096 kept the exhaustive best place for 98.2 % of the queries (the same decision for
    98.9 %), 8192 for 99.1 % (99.5 %), at 1.16 times the time (docs/performance.md)."""
    if settings.candidates:
        return settings.candidates
    grown = max(1.0, count / 1e6) ** math.log10(2)
    return int(math.ceil(CANDIDATES * grown / 1024 - 1e-9)) * 1024


def probe_for(settings: CompressedSettings, lists: int) -> int:
    """Lists a query scans: ``probe``, or :data:`PROBE_SHARE` of ``lists`` when it is 0."""
    return min(settings.probe or int(np.ceil(PROBE_SHARE * lists)), lists)


def refine_subvectors_for(dim: int) -> int:
    """The largest divisor of ``dim`` up to dim / 4 (at least 1)."""
    return next(m for m in range(max(1, dim // 4), 0, -1) if dim % m == 0)


def check_compressed(settings: CompressedSettings, dim: int, where: str = "compressed index") -> CompressedSettings:
    if settings.pq_subvectors == 0:
        settings = dataclasses.replace(settings, pq_subvectors=pq_subvectors_for(dim))
    if settings.refine_subvectors == 0:
        settings = dataclasses.replace(settings, refine_subvectors=refine_subvectors_for(dim))
    for name in ("pq_subvectors", "refine_subvectors", "candidates", "shortlist", "retrain_growth"):
        value = getattr(settings, name)
        least = 0 if name == "candidates" else 1
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ConfigError(f"{where}: {name} must be a whole number >= {least}, got {value!r}")
    if settings.lists < 0 or settings.train_points < 0 or settings.probe < 0:
        raise ConfigError(f"{where}: lists, probe and train_points must be >= 0")
    if dim % settings.pq_subvectors or settings.pq_subvectors % 2:
        raise ConfigError(
            f"{where}: pq_subvectors={settings.pq_subvectors} must be even and divide the vector " f"length {dim}"
        )
    if dim % settings.refine_subvectors:
        raise ConfigError(
            f"{where}: refine_subvectors={settings.refine_subvectors} must divide the vector length {dim}"
        )
    if not isinstance(settings.rotate, bool):
        raise ConfigError(f"{where}: rotate must be true or false, got {settings.rotate!r}")
    return settings


class CompressedIndex:
    """Fast-scan and 8-bit codes of a map's places with an exact re-rank (see the module
    docstring). The float vectors stay with the caller (a :class:`VectorFile`, a memory map or
    an array) and are passed to :meth:`sync` and :meth:`search`."""

    def __init__(self, dim: int, settings: CompressedSettings | None = None):
        import faiss

        self.dim = int(dim)
        self.settings = check_compressed(settings or CompressedSettings(), self.dim)
        self._faiss = faiss
        self._index = None  # faiss.IndexRefine: the fast-scan codes, re-ranked by the 8-bit ones
        self._parts: tuple = ()  # its two indexes (kept referenced while it uses them)
        self._rotation = None  # the learned OPQ rotation (None: the vectors as they are)
        self.trained_on = 0
        #: times this object trained its rotation, cells and codebooks (not when loaded: :meth:`load`)
        self.trainings = 0

    def __len__(self) -> int:
        return 0 if self._index is None else int(self._index.ntotal)

    def sync(self, vectors) -> None:
        """Encode the places of ``vectors`` not encoded yet; train again first when the map
        has grown ``retrain_growth``-fold since the last training (or was never trained)."""
        count = len(vectors)
        if count == 0:
            return
        if self._index is None or count >= self.settings.retrain_growth * max(self.trained_on, 1):
            self._train(vectors, count)
        if count < len(self):
            raise ConfigError(
                f"the map holds {count} places, its compressed index {len(self)}: truncate the index "
                "with the map (rebuild it)"
            )
        for start in range(len(self), count, CHUNK_ROWS):
            self._index.add(self._rotated(_rows(vectors, start, min(count, start + CHUNK_ROWS))))

    def _rotated(self, x: np.ndarray) -> np.ndarray:
        return x if self._rotation is None else self._rotation.apply(np.ascontiguousarray(x, dtype=np.float32))

    def _train(self, vectors, count: int) -> None:
        faiss = self._faiss
        s = self.settings
        # at least 39 points per cell and per 4-bit codebook entry (16 of them): faiss's k-means floor
        lists = s.lists or ivf_lists_for(count, IndexSettings(kind="ivf"))
        lists = max(1, min(lists, count // 39))
        # k-means costs lists x points: from HNSW_LISTS lists, 40 points a list (faiss's floor is 39)
        per_list = 64 if lists < HNSW_LISTS else 40
        wanted = min(count, s.train_points or max(per_list * lists, 39 * 256, 4096))
        sample = _rows(vectors, np.linspace(0, count - 1, wanted).astype(np.int64))
        with one_faiss_thread():  # see 'Training on one thread' above
            self._rotation = self._learn_rotation(sample) if s.rotate else None
        sample = self._rotated(sample)
        quantizer = self._cells(sample, lists)
        base = faiss.IndexIVFPQFastScan(quantizer, self.dim, lists, s.pq_subvectors, 4, faiss.METRIC_INNER_PRODUCT)
        base.own_fields = True
        quantizer.this.disown()
        # the finer codes: 8 bits a sub-vector once the sample can train 256 centroids each
        refine = faiss.IndexPQ(self.dim, s.refine_subvectors, pq_bits_for(wanted), faiss.METRIC_INNER_PRODUCT)
        with one_faiss_thread():  # see 'Training on one thread' above
            base.train(sample)  # the codebooks (and, below HNSW_LISTS, the cells)
            refine.train(sample)
        base.nprobe = probe_for(s, lists)
        self._index, self._parts, self.trained_on = faiss.IndexRefine(base, refine), (base, refine), count
        self.trainings += 1

    def truncate(self, count: int) -> None:
        """Forget the codes of the places from ``count`` on (the last ones: a loaded cache that
        covers more places than the map it is for); the codebooks stay as trained."""
        if count >= len(self):
            return
        tail = self._faiss.IDSelectorRange(int(count), len(self))
        for part in self._parts[:2]:
            part.remove_ids(tail)
        self._index.ntotal = int(count)

    def save(self, path: str | os.PathLike, metadata: dict | None = None) -> None:
        """Write the codes, rotation and settings to ``path`` (:mod:`fdnet.matching.compressed_file`:
        atomically, checksummed) with ``metadata`` (JSON) for the caller to check on load."""
        from fdnet.matching.compressed_file import write_codes

        if self._index is None:
            raise ConfigError("the compressed index holds no places yet: nothing to save")
        header = {
            "format": 1,
            "dim": self.dim,
            "settings": dataclasses.asdict(self.settings),
            "count": len(self),
            "trained_on": self.trained_on,
            "metadata": metadata or {},
        }
        write_codes(path, header, self._rotation, self._index)

    @classmethod
    def load(
        cls, path: str | os.PathLike, settings: CompressedSettings | None = None, header: dict | None = None
    ) -> "CompressedIndex":
        """The index :meth:`save` wrote to ``path`` (its trailer ``header`` when already read), for
        ``settings``: a file trained with other build settings is refused (DataError), as is a
        damaged one; the search settings (candidates, shortlist, probe) are ``settings``'."""
        from fdnet.matching.compressed_file import read_codes, read_header

        header = read_header(path) if header is None else header
        index = cls(int(header["dim"]), settings)
        saved = check_compressed(CompressedSettings(**header["settings"]), index.dim)
        if any(getattr(saved, k) != getattr(index.settings, k) for k in _BUILD_SETTINGS):
            raise DataError(f"{path}: the compressed codes were built with other settings")
        rotation, whole = read_codes(path, header)
        faiss = index._faiss
        refined = faiss.downcast_index(whole)
        base = faiss.downcast_index(refined.base_index) if isinstance(refined, faiss.IndexRefine) else None
        if (
            not isinstance(base, faiss.IndexIVFPQFastScan)
            or int(whole.ntotal) != int(header["count"])
            or whole.d != index.dim
            or (rotation is None) == saved.rotate
        ):
            raise DataError(f"{path}: the compressed codes file does not hold what its header says")
        base.nprobe = probe_for(index.settings, base.nlist)
        # ``whole`` owns the two indexes; the downcast views are kept with it
        index._index, index._parts = refined, (base, faiss.downcast_index(refined.refine_index), whole)
        index._rotation, index.trained_on = rotation, int(header["trained_on"])
        return index

    def _learn_rotation(self, sample: np.ndarray):
        """OPQ's rotation for the 4-bit codes, learned on at most :data:`OPQ_POINTS` of ``sample``."""
        faiss = self._faiss
        m = self.settings.pq_subvectors
        rotation = faiss.OPQMatrix(self.dim, m)
        codes = faiss.ProductQuantizer(self.dim, m, 4)  # the codes it is learned for: 4-bit
        rotation.pq = codes
        rotation.niter = OPQ_ITERATIONS
        points = sample[np.linspace(0, len(sample) - 1, min(len(sample), OPQ_POINTS)).astype(np.int64)]
        rotation.train(np.ascontiguousarray(points))
        rotation.pq = None
        return rotation

    def _cells(self, sample: np.ndarray, lists: int):
        """The coarse quantizer: a flat one (trained with the codebooks), or from HNSW_LISTS cells
        an HNSW graph over centroids found here."""
        faiss = self._faiss
        if lists < HNSW_LISTS:
            return faiss.IndexFlatIP(self.dim)
        # assigning each place to a cell by comparing it with every centroid is most of the
        # encoding time of a large map (10^7 places x 3162 cells); an HNSW graph over the
        # centroids finds the nearest one in a few hundred comparisons. It is built on one
        # thread, so the same centroids give the same graph and a resumed run the same cells.
        quantizer = faiss.IndexHNSWFlat(self.dim, 32, faiss.METRIC_INNER_PRODUCT)
        quantizer.hnsw.efSearch = 64
        # k-means as faiss's own IVF training runs it (every thread), then the graph on one
        clustering = faiss.Clustering(self.dim, lists)
        clustering.train(sample, faiss.IndexFlatIP(self.dim))
        centroids = faiss.vector_float_to_array(clustering.centroids).reshape(lists, self.dim)
        with one_faiss_thread():
            quantizer.add(centroids)
        return quantizer

    def search(
        self, queries: np.ndarray, k: int, vectors, searchable: int | None = None, below: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The best ``k`` of the first ``searchable`` places (None: all) for each query, as
        (place ids, exact dot products), each (Q, k), best first, ties to the lower id, -1 /
        -inf where the short list held fewer. The fast-scan codes propose ``candidates``, the
        8-bit codes keep ``shortlist`` of them, and their float vectors, read from ``vectors``,
        give the order and the scores. ``below``: the codes of the places from that one on are
        skipped in the scan (the same scan, fewer places), and ``searchable`` counts within the rest."""
        q = np.ascontiguousarray(queries, dtype=np.float32)
        self.sync(vectors)
        count = len(self)
        limit = count if below is None else max(0, min(int(below), count))
        searchable = limit if searchable is None else max(0, min(int(searchable), limit))
        out_ids = np.full((len(q), k), -1, np.int64)
        out_scores = np.full((len(q), k), -np.inf, np.float32)
        if searchable == 0 or k <= 0:
            return out_ids, out_scores
        # the excluded places are the last ones: ask for as many more, then drop them
        excluded = limit - searchable
        wanted = min(limit, max(self.settings.shortlist, k) + excluded)
        proposed = min(limit, max(candidates_for(self.settings, count) + excluded, wanted))
        if limit == count:
            self._index.k_factor = proposed / wanted
            _, found = self._index.search(self._rotated(q), wanted)
        else:
            import faiss

            selector = faiss.IDSelectorRange(0, limit)
            base = faiss.SearchParametersIVF(sel=selector, nprobe=self._parts[0].nprobe)
            params = faiss.IndexRefineSearchParameters(k_factor=proposed / wanted, base_index_params=base)
            _, found = self._index.search(self._rotated(q), wanted, params=params)
        for row, ids in enumerate(found):
            ids = np.unique(ids[(ids >= 0) & (ids < searchable)])  # sorted: the file is read in order
            if not len(ids):
                continue
            exact = _rows(vectors, ids) @ q[row]
            order = np.lexsort((ids, -exact))[:k]
            out_ids[row, : len(order)] = ids[order]
            out_scores[row, : len(order)] = exact[order]
        return out_ids, out_scores

    def memory_bytes(self) -> int:
        """What the index holds in memory: both codes and the ids, lists' centroids, codebooks (as
        faiss serialises them, counted without a copy) and the rotation."""
        if self._index is None:
            return 0
        rotation = 0 if self._rotation is None else 4 * self.dim * self.dim
        return serialised_bytes(self._index) + rotation

    def describe(self) -> dict:
        s = self.settings
        out = {
            "kind": "opq-ivfpq-fastscan+pq8" if s.rotate else "ivfpq-fastscan+pq8",
            "dim": self.dim,
            "count": len(self),
            "trained_on": self.trained_on,
            "bytes_per_code": s.pq_subvectors // 2,
            "refine_bytes_per_code": s.refine_subvectors,
            "candidates": candidates_for(s, len(self)),
            "shortlist": s.shortlist,
        }
        if self._index is not None:
            out["lists"] = int(self._parts[0].nlist)
            out["probe"] = int(self._parts[0].nprobe)
        return out


def _rows(vectors, where, stop: int | None = None) -> np.ndarray:
    """Rows of ``vectors`` as a float32 array in memory: ``where`` to ``stop`` (a range), or at
    the sorted ids ``where``; a :class:`VectorFile` is read with ``pread``."""
    if stop is not None:
        if isinstance(vectors, VectorFile):
            return vectors.read(where, stop)
        return np.ascontiguousarray(vectors[where:stop], dtype=np.float32)
    if isinstance(vectors, VectorFile):
        return vectors.rows(where)
    return np.ascontiguousarray(vectors[where], dtype=np.float32)
