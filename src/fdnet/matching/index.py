"""Indexed nearest-neighbour search with faiss, for maps of up to millions of places.

Only for descriptors whose similarity is a dot product (``dot_product_similarity``); others
(SAD, DBoW's L1 score, Landmarks) raise a clear error rather than silently ranking by the
wrong measure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fdnet.errors import ConfigError

INDEX_KINDS = ("flat", "hnsw", "ivf")


@dataclass
class IndexSettings:
    #: flat = exact inner product; hnsw = graph (no training, fast, approximate);
    #: ivf = inverted lists (needs training, for very large maps)
    kind: str = "flat"
    hnsw_neighbors: int = 32
    hnsw_ef_search: int = 128
    ivf_lists: int = 0  # 0 = about 4*sqrt(N)
    ivf_probe: int = 16


class VectorIndex:
    """Inner-product index over (N, D) float32 vectors (cosine for unit vectors)."""

    def __init__(self, dim: int, settings: IndexSettings | None = None):
        import faiss

        self.settings = settings or IndexSettings()
        if self.settings.kind not in INDEX_KINDS:
            raise ConfigError(f"unknown index kind {self.settings.kind!r}; choose from {', '.join(INDEX_KINDS)}")
        self.dim = int(dim)
        self._faiss = faiss
        self._index = None
        self._pending: list[np.ndarray] = []
        if self.settings.kind == "flat":
            self._index = faiss.IndexFlatIP(self.dim)
        elif self.settings.kind == "hnsw":
            self._index = faiss.IndexHNSWFlat(self.dim, self.settings.hnsw_neighbors, faiss.METRIC_INNER_PRODUCT)
            self._index.hnsw.efSearch = self.settings.hnsw_ef_search

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
        if self.settings.kind == "ivf" and (self._index is None or not self._index.is_trained):
            # IVF needs training data; defer until the first search (or enough vectors).
            self._pending.append(v)
            return
        self._index.add(v)

    def _build_ivf(self) -> None:
        data = np.concatenate(self._pending) if self._pending else np.zeros((0, self.dim), np.float32)
        n_lists = self.settings.ivf_lists or max(1, int(4 * np.sqrt(max(len(data), 1))))
        # faiss's k-means wants >= 39 training points per list; fewer lists beat a poor quantizer.
        n_lists = max(1, min(n_lists, len(data) // 39))
        quantizer = self._faiss.IndexFlatIP(self.dim)
        index = self._faiss.IndexIVFFlat(quantizer, self.dim, n_lists, self._faiss.METRIC_INNER_PRODUCT)
        if len(data):
            index.train(data)
            index.add(data)
        index.nprobe = min(self.settings.ivf_probe, n_lists)
        self._index, self._pending, self._quantizer = index, [], quantizer

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Best ``k`` per query: (indices (Q, k) int64, scores (Q, k) float32); -1 where fewer exist."""
        if self.settings.kind == "ivf" and self._pending:
            self._build_ivf()
        q = self._check(queries)
        if len(self) == 0:
            raise ConfigError("the index is empty: add reference vectors before searching")
        scores, indices = self._index.search(q, int(min(k, len(self))))
        return indices.astype(np.int64), scores.astype(np.float32)

    def reconstruct_all(self) -> np.ndarray:
        """All stored vectors in insertion order (for saving a database)."""
        if self.settings.kind == "ivf" and self._pending:
            self._build_ivf()
        n = self._index.ntotal
        if n == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        if self.settings.kind == "ivf":
            self._index.make_direct_map()
        return np.asarray(self._index.reconstruct_n(0, n), dtype=np.float32)
