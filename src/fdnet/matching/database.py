"""A persistent place database for loop closure and relocalisation.

Holds one vector per place with its name (image file) and optional position, answers
"which stored places look like this?" with ranked candidates and scores, and saves/loads
atomically. It records which descriptor made its vectors (method and settings), so a database
is never queried with vectors from a different model.

Search uses a faiss index for dot-product descriptors (exact ``flat`` by default, ``hnsw``/``ivf``
for large maps) and the descriptor's own similarity otherwise.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from fdnet.errors import ConfigError, DataError
from fdnet.io import atomic_path, atomic_write_text
from fdnet.matching.index import IndexSettings, VectorIndex
from fdnet.matching.similarity import top_k

FORMAT_VERSION = 1


@dataclass
class Match:
    index: int
    name: str
    score: float
    position: tuple[float, float] | None = None


@dataclass
class PlaceDatabase:
    dim: int
    method: str
    method_settings: dict = field(default_factory=dict)
    dot_product: bool = True
    index_settings: IndexSettings = field(default_factory=IndexSettings)
    similarity: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
    #: how to rebuild the descriptor (``fdnet.descriptors.create(method, **method_options)``)
    method_options: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.names: list[str] = []
        self.positions: list[tuple[float, float] | None] = []
        self._vectors: list[np.ndarray] = []
        self._index = VectorIndex(self.dim, self.index_settings) if self.dot_product else None

    @classmethod
    def for_descriptor(cls, descriptor, index: IndexSettings | None = None,
                       method_options: dict | None = None) -> "PlaceDatabase":
        return cls(method_options=dict(method_options or {}),dim=descriptor.dim, method=descriptor.name, method_settings=descriptor.settings(),
                   dot_product=descriptor.dot_product_similarity,
                   index_settings=index or IndexSettings(),
                   similarity=None if descriptor.dot_product_similarity else descriptor.similarity)

    def __len__(self) -> int:
        return len(self.names)

    def add(self, vectors: np.ndarray, names: Sequence[str],
            positions: Sequence[tuple[float, float]] | np.ndarray | None = None) -> None:
        v = np.asarray(vectors, dtype=np.float32)
        if v.ndim != 2 or v.shape[1] != self.dim:
            raise ConfigError(f"database holds {self.dim}-d vectors ({self.method}), got shape {v.shape}")
        if len(names) != len(v):
            raise ConfigError(f"{len(v)} vectors but {len(names)} names")
        if positions is not None and len(positions) != len(v):
            raise ConfigError(f"{len(v)} vectors but {len(positions)} positions")
        self.names.extend(str(n) for n in names)
        self.positions.extend([tuple(map(float, p)) for p in positions] if positions is not None else [None] * len(v))
        self._vectors.append(v)
        if self._index is not None:
            self._index.add(v)

    @property
    def vectors(self) -> np.ndarray:
        if not self._vectors:
            return np.zeros((0, self.dim), dtype=np.float32)
        if len(self._vectors) > 1:
            self._vectors = [np.concatenate(self._vectors)]
        return self._vectors[0]

    def query(self, vectors: np.ndarray, k: int = 5, exclude_last: int = 0) -> list[list[Match]]:
        """Top-``k`` stored places per query vector, best first.

        ``exclude_last`` ignores the most recently added places: for loop closure a robot's
        previous few frames always look alike and must not count as revisits.
        """
        if len(self) == 0:
            raise ConfigError("the place database is empty: add places before querying")
        q = np.asarray(vectors, dtype=np.float32)
        if q.ndim == 1:
            q = q[None]
        if q.shape[1] != self.dim:
            raise ConfigError(f"database holds {self.dim}-d vectors ({self.method}), got queries of shape {q.shape}")
        searchable = len(self) - max(0, exclude_last)
        if searchable <= 0:
            return [[] for _ in range(len(q))]
        want = min(k, searchable)
        if self._index is not None:
            # Ask for extra candidates, then drop the excluded (most recent) ones.
            idx, scores = self._index.search(q, min(len(self), want + max(0, exclude_last)))
        else:
            if self.similarity is None:
                raise ConfigError(f"method {self.method!r} compares vectors with its own similarity; "
                                  "build the database with PlaceDatabase.for_descriptor(descriptor)")
            idx, scores = top_k(q, self.vectors[:searchable], want, similarity=self.similarity)
        out = []
        for row_i, row_s in zip(idx, scores):
            keep = [(int(i), float(s)) for i, s in zip(row_i, row_s) if 0 <= i < searchable][:want]
            out.append([Match(i, self.names[i], s, self.positions[i]) for i, s in keep])
        return out

    # ------------------------------------------------------------------ persistence
    def save(self, folder: str | os.PathLike) -> None:
        """Write ``vectors.npy`` and ``database.json`` (metadata last, so a crash mid-save
        leaves the previous database readable)."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_path(folder / "vectors.npy") as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, self.vectors, allow_pickle=False)
        meta = {
            "format_version": FORMAT_VERSION,
            "dim": self.dim,
            "method": self.method,
            "method_settings": self.method_settings,
            "method_options": self.method_options,
            "dot_product": self.dot_product,
            "index": vars(self.index_settings),
            "names": self.names,
            "positions": self.positions,
        }
        atomic_write_text(folder / "database.json", json.dumps(meta))

    @classmethod
    def load(cls, folder: str | os.PathLike, descriptor=None) -> "PlaceDatabase":
        """Load a saved database; pass the ``descriptor`` for methods with their own similarity
        (and to check the database was built by the same method and settings)."""
        folder = Path(folder)
        meta_path, vec_path = folder / "database.json", folder / "vectors.npy"
        try:
            meta = json.loads(meta_path.read_text())
        except FileNotFoundError:
            raise DataError(f"{meta_path}: not found; is {folder} a place database?") from None
        except json.JSONDecodeError as exc:
            raise DataError(f"{meta_path}: corrupt database metadata ({exc})") from None
        try:
            vectors = np.load(vec_path, allow_pickle=False)
        except (FileNotFoundError, ValueError, OSError) as exc:
            raise DataError(f"{vec_path}: cannot read database vectors ({exc})") from None
        if vectors.shape != (len(meta["names"]), meta["dim"]):
            raise DataError(f"{vec_path}: holds {vectors.shape} but {meta_path} describes "
                            f"{len(meta['names'])} places of dimension {meta['dim']}")
        if descriptor is not None and (descriptor.name != meta["method"]):
            raise ConfigError(f"{folder}: database was built with method {meta['method']!r}, "
                              f"not {descriptor.name!r}")
        db = cls(dim=meta["dim"], method=meta["method"], method_settings=meta.get("method_settings", {}),
                 method_options=meta.get("method_options", {}),
                 dot_product=meta["dot_product"], index_settings=IndexSettings(**meta.get("index", {})),
                 similarity=None if descriptor is None or descriptor.dot_product_similarity else descriptor.similarity)
        positions = [tuple(p) if p is not None else None for p in meta.get("positions", [])]
        db.add(vectors, meta["names"], None)
        db.positions = positions or [None] * len(db.names)
        return db
