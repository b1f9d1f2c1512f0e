"""A map's vectors kept in a vector file instead of memory, read a few rows at a time.

:class:`FileRows` is what a :class:`~fdnet.matching.place_map.PlaceMap` holds as its vectors
when its place database keeps them in a :class:`~fdnet.matching.compressed.VectorFile`
(:mod:`fdnet.matching.database.vector_store`): the first rows are the file's (read with
``pread`` when asked for, nothing kept), and the rows appended since (a loop-closure frame not
yet stored) stay in memory until the database has stored them (:meth:`FileRows.stored`). It
reads like an array (``rows[a:b]``, ``rows[ids]``, ``rows[i]``, ``len``), so the indexed
loop-closure search and :class:`~fdnet.matching.compressed.CompressedIndex` read only the rows
they need; ``np.asarray(rows)`` reads them all (exhaustive search over such a map).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from fdnet.errors import ConfigError
from fdnet.matching.place_map import GrowingArray


class FileRows:
    """The first ``stored`` rows of the vector file ``source()`` returns (the database's current
    one: it may be opened again as other processes add), then rows appended here, in memory.
    :class:`~fdnet.matching.place_map.GrowingArray`'s interface (``len``, ``append``,
    ``extend``, ``truncate``, ``view``) plus reading by index (see the module docstring)."""

    def __init__(self, source: Callable[[], object], stored: int, dim: int, tail: np.ndarray | None = None):
        self._source = source
        self._stored = int(stored)
        self.dim = int(dim)
        self._tail = GrowingArray(self.dim, tail)

    def __len__(self) -> int:
        return self._stored + len(self._tail)

    @property
    def in_memory(self) -> int:
        """Rows held in memory (appended, not yet stored in the file)."""
        return len(self._tail)

    def append(self, row) -> None:
        self._tail.append(row)

    def extend(self, rows: np.ndarray) -> None:
        self._tail.extend(rows)

    def truncate(self, count: int) -> None:
        """Forget the rows from ``count`` on (the file is not touched: its rows are stored places)."""
        count = max(0, min(int(count), len(self)))
        if count <= self._stored:
            self._stored = count
            self._tail.truncate(0)
        else:
            self._tail.truncate(count - self._stored)

    def stored(self, count: int) -> None:
        """The file now holds the first ``count`` rows (an add stored them): read them from there
        and drop their copies from memory."""
        count = int(count)
        if not self._stored <= count <= len(self):
            raise ConfigError(f"{count} rows stored, but this map holds {len(self)} ({self._stored} in its file)")
        rest = self._tail.view()[count - self._stored :].copy()
        self._tail = GrowingArray(self.dim, rest)
        self._stored = count

    def view(self, count: int | None = None) -> "FileRows":
        """The first ``count`` rows (default all), reading the same file."""
        if count is None or int(count) >= len(self):
            return self
        count = max(0, int(count))
        stored = min(self._stored, count)
        return FileRows(self._source, stored, self.dim, self._tail.view()[: count - stored])

    def __getitem__(self, key) -> np.ndarray:
        if isinstance(key, slice):
            start, stop, step = key.indices(len(self))
            if step != 1:
                return self[np.arange(start, stop, step)]
            stop = max(start, stop)
            parts = []
            if start < self._stored:
                parts.append(self._source().read(start, min(stop, self._stored)))
            if stop > self._stored:
                parts.append(self._tail.view()[max(start - self._stored, 0) : stop - self._stored])
            return np.concatenate(parts) if len(parts) > 1 else parts[0] if parts else self._empty()
        if isinstance(key, (int, np.integer)):
            return self[np.array([int(key)])][0]
        ids = np.asarray(key, np.int64).reshape(-1)
        if len(ids) and (ids.min() < 0 or ids.max() >= len(self)):
            raise IndexError(f"row ids must be in [0, {len(self)})")
        out = np.empty((len(ids), self.dim), np.float32)
        in_file = ids < self._stored
        if in_file.any():
            out[in_file] = self._source().rows(ids[in_file])
        if not in_file.all():
            out[~in_file] = self._tail.view()[ids[~in_file] - self._stored]
        return out

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        rows = self[0 : len(self)]
        return rows if dtype is None else rows.astype(dtype)

    def _empty(self) -> np.ndarray:
        return np.zeros((0, self.dim), np.float32)
